"""`python -m jaxems.demo --out out`: the main job on the bundled data (what `make demo` runs).

1. Level 3 velocity prediction on every bundled route (one `vmap`): a summary table and one
   PNG per route (v(s) against the speed limit and the elevation, and P_d(t)).
2. The fleet sweep of `examples/demo_sweep.toml` (bundled routes x masses x battery sizes x
   conventional / baseline / multilevel) on a local Dask cluster, with its report
   (`OUT/demo/report.html`, printed first).
3. The Table 8 comparison from the sweep: fuel per strategy and route at 20 t, 4 MJ.
4. The plant traces of the multi-level EMS on the short track at 25 t (Figure A3).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import jax
import numpy as np

from .io import list_routes, load_route, route_name
from .levels.velocity import Prediction, energy_summary, predict_batch
from .params import load_vehicle
from .route import Route, elevation, route_summary


def _member(pred: Prediction, b: int) -> Prediction:
    return jax.tree_util.tree_map(lambda x: np.asarray(x)[b], pred)


def plot_prediction(path: Path, name: str, route: Route, pred: Prediction) -> None:
    """Write a PNG: v(s) with the speed limit and elevation (top), P_d(t) (bottom)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    prof = pred.profile
    n = int(np.sum(route.mask))
    s_km = np.asarray(prof.s)[:n] / 1e3
    fig, (ax1, ax3) = plt.subplots(2, 1, figsize=(10, 6.5), constrained_layout=True)
    ax1.plot(s_km, np.asarray(route.vmax)[:n] * 3.6, color="0.6", lw=1, label="speed limit")
    ax1.plot(s_km, np.asarray(prof.v)[:n] * 3.6, color="C0", lw=1.2, label="Level 3 v(s)")
    stops = np.flatnonzero(np.asarray(route.stop)[:n] > 0)
    ax1.plot(s_km[stops], np.zeros(len(stops)), "v", color="C3", ms=5, label="stop")
    ax1.set_ylim(-3, 1.1 * float(np.max(np.asarray(route.vmax)[:n])) * 3.6 + 1)
    ax1.set_xlabel("distance (km)")
    ax1.set_ylabel("speed (km/h)")
    ax1.set_title(f"{name}: Level 3 velocity prediction")
    ax2 = ax1.twinx()
    ax2.fill_between(s_km, elevation(route)[:n], color="C2", alpha=0.15, lw=0)
    ax2.set_ylabel("elevation (m)", color="C2")
    ax1.set_zorder(ax2.get_zorder() + 1)
    ax1.patch.set_visible(False)
    ax1.legend(loc="lower right", fontsize=8)
    m = np.asarray(pred.mask)
    ax3.plot(np.asarray(pred.t)[m], np.asarray(pred.P_d)[m] / 1e3, color="C1", lw=0.8)
    ax3.axhline(0, color="0.5", lw=0.5)
    ax3.set_xlabel("time (s)")
    ax3.set_ylabel("P_d (kW)")
    ax3.set_title("driveline power demand (mean over each 1 s step)")
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    """Run Level 3 on the bundled routes, print a table, write plots to --out."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="out", help="output folder for plots (default out/)")
    ap.add_argument("--vehicle", default="reference_truck", help="vehicle name or TOML file")
    ap.add_argument("--workers", type=int, default=2,
                    help="Dask workers for the sweep (0: in-process; default 2)")
    ap.add_argument("--quiet", action="store_true", help="no progress bar")
    ap.add_argument("--level3-only", action="store_true", help="only the Level 3 part")
    args = ap.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if not args.level3_only:
        print(f"jaxems demo: the report will be at {out / 'demo' / 'report.html'}", flush=True)
    t0 = time.perf_counter()
    vp = load_vehicle(args.vehicle)
    paths = list_routes()
    routes = [load_route(p) for p in paths]
    names = [route_name(p) for p in paths]
    pred = predict_batch(routes, vp)
    jax.block_until_ready(pred)
    t_pred = time.perf_counter() - t0
    print(
        f"jaxems demo: Level 3 velocity prediction, {args.vehicle} "
        f"({float(vp.mass) / 1000:g} t, v0 = {float(vp.v_cruise) * 3.6:g} km/h)"
    )
    head = (
        f"{'route':<18} {'km':>7} {'trip s':>7} {'km/h':>6} {'grad %':>13} {'stops':>9} "
        f"{'E+ MJ':>7} {'E- MJ':>7} {'ok':>3}"
    )
    print(head)
    print("-" * len(head))
    for b, name in enumerate(names):
        p = _member(pred, b)
        info = route_summary(routes[b])
        e = energy_summary(p)
        print(
            f"{name:<18} {info['length_m'] / 1e3:>7.2f} {e['trip_time_s']:>7.0f} "
            f"{e['mean_speed_km_h']:>6.1f} "
            f"{info['gradient_min_pct']:>+6.1f}..{info['gradient_max_pct']:<+5.1f} "
            f"{info['stops']:>3} {info['stop_time_s']:>4.0f}s "
            f"{e['energy_traction_MJ']:>7.1f} {e['energy_braking_MJ']:>7.1f} "
            f"{'yes' if e['feasible'] else 'NO':>3}"
        )
        plot_prediction(out / f"level3_{name}.png", name, routes[b], p)
    print(
        f"E+ traction energy, E- braking energy at the wheels (sum of P_d dt). "
        f"Level 3 for {len(names)} routes in {t_pred:.1f} s (one vmap); plots in {out}/"
    )
    if args.level3_only:
        return 0
    from .sweep import load_sweep, run_demo

    print()
    summary = run_demo(out=out / "demo", workers=args.workers or None, quiet=args.quiet)
    print()
    print(table8_text(load_sweep(summary.out)))
    print()
    write_traces(out, vehicle=args.vehicle)
    print(f"report: {out / 'demo' / 'report.html'}")
    return 0


def table8_text(df, mass_kg: float = 20000.0, battery_MJ: float = 4.0) -> str:
    """The Table 8 comparison from a sweep: l/100 km and saving (%) against conventional (on
    fuel corrected for the remaining battery energy) per route, at one mass and battery."""
    sel = df[(df.mass_kg == mass_kg) & (df.battery_MJ == battery_MJ)]
    strategies = [s for s in ("conventional", "baseline", "multilevel", "multilevel-mpc",
                              "dp-bound") if s in set(sel.strategy)]
    lines = [f"Table 8 comparison ({mass_kg / 1000:g} t, {battery_MJ:g} MJ battery): "
             f"l/100 km (saving % vs conventional, corrected for delta E_b)"]
    head = f"{'route':<18}" + "".join(f"{s:>22}" for s in strategies)
    lines += [head, "-" * len(head)]
    for route, g in sel.groupby("route", sort=True):
        cells = []
        for s in strategies:
            r = g[g.strategy == s]
            if r.empty:
                cells.append(f"{'-':>22}")
                continue
            r = r.iloc[0]
            sv = r.get("saving_vs_conventional_pct", float("nan"))
            note = "" if r.status == "ok" else f" {r.status}"
            cells.append(f"{r.fuel_l_per_100km:>12.2f} ({sv:+6.1f} %){note}")
        lines.append(f"{route:<18}" + "".join(cells))
    lines.append("paper (long haul, 25 t): 33.0 / 31.1 (-5.8 %) / 30.7 (-7.0 %) l/100 km")
    return "\n".join(lines)


def write_traces(out: Path, vehicle: str = "reference_truck") -> None:
    """Figure A3 of the paper from our model: multilevel (2 iterations) on the short track."""
    from .params import load_vehicle, with_overrides
    from .report import plot_run
    from .strategies import simulate

    vp = with_overrides(load_vehicle(vehicle), mass_kg=25000.0)
    res = simulate("short_track", vp, "multilevel")
    path = out / "traces_short_track_multilevel.png"
    plot_run(res, vp, "multi-level EMS, 25 t (iteration 1)", path)
    d = res.as_dict()
    print(f"short track, 25 t, multilevel: {d['fuel_J'] / 1e6:.2f} MJ fuel, "
          f"delta E_b {d['delta_Eb_J'] / 1e6:+.2f} MJ; traces in {path}")


if __name__ == "__main__":
    sys.exit(main())
