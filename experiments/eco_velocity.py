"""Eco-driving against the paper's Level 3: multilevel-eco vs multilevel at equal trip time.

For each bundled VECTO route (20 t reference truck) both strategies run on the same plant:
``multilevel`` drives Level 3's predicted speed (section 6), ``multilevel-eco`` the speed that
`velocity.optimize_velocity` finds (fuel-equivalent energy at Level 2's costate plus lambda_t
times the trip time), lambda_t found so that its trip time equals Level 3's. Fuel is compared
corrected for the battery energy left over (J + lambda_b dE_b), as in Table 8. One PNG per
route shows both speed profiles over distance above the road's elevation.

    .venv/bin/python experiments/eco_velocity.py [--routes LongHaul,...] [--mass 20000]
                                                 [--out out/eco] [--json]

`--json` prints ``{"rows": [...], "plots": [...]}`` on stdout; progress goes to stderr.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from jax import config

config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from jaxems import powertrain as pt  # noqa: E402
from jaxems.cli import comma_list, number, print_result  # noqa: E402
from jaxems.cli import format_or_dash as _f  # noqa: E402  (a number, or "-" for None)
from jaxems.io import load_route  # noqa: E402
from jaxems.params import load_vehicle, with_overrides  # noqa: E402
from jaxems.strategies import simulate  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from table7 import _log, _num  # noqa: E402  (the same formatting as Table 7)

DEFAULT_ROUTES = ("LongHaul", "RegionalDelivery", "UrbanDelivery")
STRATS = ("multilevel", "multilevel-eco")


def run_eco(routes=DEFAULT_ROUTES, mass_kg: float = 20000.0, dt: float = 1.0,
            vehicle: str = "reference_truck", out_dir: str | None = None) -> dict:
    """Both strategies on every route; rows as `Result.as_dict()` plus the corrected fuel in
    l/100 km, the Level 3 trip time, lambda_t (eco rows) and saving_pct (corrected fuel of eco
    against multilevel on the same route). Writes one plot per route when out_dir is given."""
    vp = with_overrides(load_vehicle(vehicle), mass_kg=mass_kg)
    for route in routes:  # every route file exists and parses before anything compiles
        load_route(route)
    rows, plots = [], []
    for route in routes:
        res = {}
        for s in STRATS:
            t0 = time.perf_counter()
            r = simulate(route, vp, s, dt=dt)
            d = r.as_dict()
            _log(f"eco: {d['route']:<16} {s:<15} {time.perf_counter() - t0:7.1f} s  "
                 f"{d['fuel_l_per_100km']:6.2f} l/100 km  trip {d['trip_time_s']:.0f} s  "
                 f"status {d['status']}")
            d["fuel_corrected_l_per_100km"] = (
                float(pt.fuel_litres(vp, d["fuel_corrected_J"])) / (d["length_m"] / 1e5))
            d["predicted_trip_time_s"] = float(r.prediction.trip_time)
            if s == "multilevel-eco":
                d["lambda_t_J_per_s"] = float(r.extra.lambda_t)
                d["level3_trip_time_s"] = float(r.extra.level3_trip_time)
            res[s] = (r, d)
            rows.append(d)
        base, eco = res["multilevel"][1], res["multilevel-eco"][1]
        eco["saving_pct"] = 100.0 * (eco["fuel_corrected_J"] / base["fuel_corrected_J"] - 1.0)
        eco["trip_time_ratio"] = eco["trip_time_s"] / base["trip_time_s"]
        base["saving_pct"], base["trip_time_ratio"] = 0.0, 1.0
        if out_dir is not None:
            plots.append(plot_route(route, {s: res[s][0] for s in STRATS}, Path(out_dir)))
    for r in rows:
        for k, v in list(r.items()):
            if isinstance(v, float):
                r[k] = _num(v)
    return {"vehicle": vehicle, "mass_kg": float(mass_kg), "dt_s": float(dt), "rows": rows,
            "plots": plots}


def plot_route(route: str, results: dict, out: Path) -> str:
    """v(s) of every strategy's prediction above the road's elevation; returns the PNG path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    r = load_route(route)
    m = np.asarray(r.mask)
    ds = float(r.ds)
    grade = np.asarray(r.grade)[m]
    s_km = np.arange(grade.size) * ds / 1e3
    elev = np.concatenate([[0.0], np.cumsum(grade[:-1] * ds)])
    fig, (ax, ax2) = plt.subplots(2, 1, sharex=True, figsize=(11, 6),
                                  gridspec_kw={"height_ratios": [3, 1]})
    ax.plot(s_km, np.asarray(r.vmax)[m] * 3.6, color="0.6", lw=0.8, ls=":", label="speed limit")
    for (name, res), lw in zip(results.items(), (2.0, 0.9), strict=False):
        prof = res.prediction.profile
        pm = np.asarray(prof.mask)
        ax.plot(np.asarray(prof.s)[pm] / 1e3, np.asarray(prof.v)[pm] * 3.6, lw=lw, label=name)
    ax.set_ylabel("v [km/h]")
    ax.legend(loc="lower right")
    ax.set_title(f"{route}: predicted speed, Level 3 (multilevel) and eco-driving")
    ax2.fill_between(s_km, elev, elev.min(), color="0.8")
    ax2.set_ylabel("elevation [m]")
    ax2.set_xlabel("distance [km]")
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"eco_{route}.png"
    tmp = path.with_name(path.name + ".tmp.png")
    fig.tight_layout()
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    tmp.replace(path)  # no half-written plot
    return str(path)


def format_table(out: dict) -> str:
    head = (f"{'route':<16} {'strategy':<15} {'l/100km':>8} {'corr.':>7} {'vs ML %':>8} "
            f"{'trip [s]':>8} {'t ratio':>7} {'dE_b [MJ]':>9} {'lambda_t':>9}  status")
    lines = [f"Eco-driving: {out['vehicle']}, {out['mass_kg']:.0f} kg (corr. = fuel + lambda_b "
             f"dE_b; vs ML: corrected fuel against multilevel)", head, "-" * len(head)]
    for r in out["rows"]:
        lines.append(
            f"{r['route']:<16} {r['strategy']:<15} {_f(r['fuel_l_per_100km'], '8.2f')} "
            f"{_f(r['fuel_corrected_l_per_100km'], '7.2f')} {_f(r['saving_pct'], '+8.2f')} "
            f"{_f(r['trip_time_s'], '8.0f')} {_f(r['trip_time_ratio'], '7.4f')} "
            f"{_f(r['delta_Eb_J'] / 1e6, '+9.3f')} {_f(r.get('lambda_t_J_per_s'), '9.1f')}  "
            f"{r['status']}")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--routes", default=",".join(DEFAULT_ROUTES),
                    help="comma-separated route files or bundled names (the VECTO cycles)")
    ap.add_argument("--mass", type=number, default=20000.0, help="vehicle mass in kg (20000)")
    ap.add_argument("--vehicle", default="reference_truck", help="vehicle name or TOML file")
    ap.add_argument("--dt", type=number, default=1.0, help="time step in s (1)")
    ap.add_argument("--out", default="out/eco", help="folder of the plots (out/eco)")
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    args = ap.parse_args(argv)
    routes = comma_list(args.routes, "--routes")
    return print_result("eco_velocity", lambda: run_eco(routes, args.mass, args.dt,
                                                        args.vehicle, args.out),
                        args.json, format_table)


if __name__ == "__main__":
    from jaxems.cli import script_main

    sys.exit(script_main("eco_velocity", main))
