"""`python -m jaxems.demo --out out`: the main job on the bundled data (what `make demo` runs).

For now: Level 3 velocity prediction on every bundled route for the reference truck, batched
with `vmap` (one compilation for all routes). Prints a summary table and writes one PNG per
route to the output folder: v(s) against the speed limit and the elevation, and P_d(t).
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
    args = ap.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
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
    return 0


if __name__ == "__main__":
    sys.exit(main())
