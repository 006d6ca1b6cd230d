"""One strategy's options tried across vehicles: per combination of option values and route,
corrected fuel summed over a grid of masses and battery sizes, the runs that miss the charge
and the trips that run long.

An option tuned on one vehicle can trade charge sustaining or trip time elsewhere; this script
puts each combination of values (the Cartesian product of the `--set` lists) on the demo
sweep's vehicles (20 / 30 / 40 t x 2 / 4 / 8 MJ) and routes by default. Per combination and
route: corrected fuel (fuel + lambda_b delta E_b) summed over the vehicles, how many end more
than 1 % of their battery from their start, how many trips take more than 1 % longer than
their Level 3 prediction, and the longest. Float64; one `simulate_batch` per combination and
route. A combination that differs only in the numbers of `strategies.TRACED_OPTIONS` (the
A-ECMS's five among them) runs the program compiled for the first; the other options are
compiled in, each combination anew.

    .venv/bin/python experiments/option_grid.py --strategy baseline --set ecms_horizon=1,3
        [--set dwell=3,5] [--routes short_track,LongHaul,RegionalDelivery,UrbanDelivery]
        [--masses 20000,30000,40000] [--batteries 2,4,8] [--vehicle reference_truck] [--json]

`--json` prints one JSON object ``{"strategy", ..., "rows": [...]}`` on stdout; progress goes
to stderr.
"""

from __future__ import annotations

import argparse
import itertools
import sys
import time
from pathlib import Path

import numpy as np
from jax import config

config.update("jax_enable_x64", True)

from jaxems.cli import comma_list, print_result  # noqa: E402
from jaxems.params import load_vehicle, stack_vehicles, with_overrides  # noqa: E402
from jaxems.report import CHARGE_SHARE, TRIP_SHARE, off_charge, trip_vs_level3_pct  # noqa: E402
from jaxems.strategies import check_strategy, simulate_batch  # noqa: E402
from jaxems.sweep import option_pairs  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from charge_grid import _floats  # noqa: E402
from table7 import _num  # noqa: E402

DEFAULT_ROUTES = ("short_track", "LongHaul", "RegionalDelivery", "UrbanDelivery")


def option_values(sets: list[str], strategy: str) -> list[tuple[str, list]]:
    """[(name, [values])] from "NAME=V1,V2" strings, each value checked as `jaxems simulate
    --option` checks it, for `strategy`; ValueError naming the bad one."""
    out = []
    for text in sets:
        name, sep, values = text.partition("=")
        if not sep or not name.strip() or not comma_list(values):
            raise ValueError(f"--set {text!r}: expected NAME=VALUE[,VALUE...]")
        vals = [option_pairs([f"{name.strip()}={v}"], "--set", strategy)[name.strip()]
                for v in comma_list(values)]
        out.append((name.strip(), vals))
    if len({n for n, _ in out}) != len(out):
        raise ValueError("--set: an option given twice")
    return out


def run_grid(strategy: str, sets: list[tuple[str, list]], routes=DEFAULT_ROUTES,
             masses=(20000.0, 30000.0, 40000.0), batteries=(2.0, 4.0, 8.0),
             vehicle: str = "reference_truck") -> dict:
    """Every combination of `sets`' values x route on the vehicles masses x batteries (MJ):
    {"strategy", "routes", "masses_kg", "batteries_MJ", "rows": [...]}, a row per combination
    and route."""
    check_strategy(strategy)
    base = load_vehicle(vehicle)
    grid = [(m, b) for m in masses for b in batteries]
    vps = stack_vehicles([with_overrides(base, mass_kg=m, battery_MJ=b) for m, b in grid])
    names = [n for n, _ in sets]
    rows = []
    for combo in itertools.product(*(v for _, v in sets)):
        opts = dict(zip(names, combo, strict=True))
        for route in routes:
            t = time.perf_counter()
            out = simulate_batch(route, vps, strategy, options=opts)
            ok = out["status"] == "ok"
            pct = trip_vs_level3_pct(out["trip_time_s"], out["level3_trip_time_s"])
            rows.append({
                "options": opts, "route": route, "runs": len(grid),
                "not_ok": int(np.sum(~ok)),
                "fuel_corrected_J": _num(np.sum(out["fuel_corrected_J"][ok])),
                "off_charge": int(np.sum(ok & off_charge(out["delta_Eb_J"], vps.E_b_max))),
                "trip_long": int(np.sum(ok & (pct > 100 * TRIP_SHARE))),
                "trip_pct_max": _num(np.max(pct[ok])) if np.any(ok) else None,
            })
            print(f"option_grid: {opts} {route:16s} {rows[-1]['fuel_corrected_J'] / 1e6:9.2f} MJ, "
                  f"{rows[-1]['off_charge']} off charge, {rows[-1]['trip_long']} long "
                  f"({time.perf_counter() - t:.1f} s)", file=sys.stderr, flush=True)
    return {"strategy": strategy, "vehicle": vehicle, "routes": list(routes),
            "masses_kg": list(masses), "batteries_MJ": list(batteries),
            "charge_share_pct": 100 * CHARGE_SHARE, "trip_share_pct": 100 * TRIP_SHARE,
            "rows": rows}


def format_table(out: dict) -> str:
    """A line per combination and route; the combination's totals after its routes."""
    lines = [f"{out['strategy']} on {len(out['masses_kg']) * len(out['batteries_MJ'])} "
             f"vehicles ({out['masses_kg']} kg x {out['batteries_MJ']} MJ): corrected fuel "
             f"summed, runs more than {out['charge_share_pct']:g} % of the battery off, trips "
             f"more than {out['trip_share_pct']:g} % longer than Level 3's (the longest)"]
    head = f"{'options':30s} {'route':16s} {'fuel MJ':>10s} {'off':>4s} {'long':>5s} {'max %':>7s}"
    lines += [head, "-" * len(head)]
    by_combo: dict[str, list] = {}
    for r in out["rows"]:
        combo = " ".join(f"{k}={v}" for k, v in r["options"].items()) or "(defaults)"
        by_combo.setdefault(combo, []).append(r)
    for combo, rows in by_combo.items():
        for r in rows:
            worst = "-" if r["trip_pct_max"] is None else f"{r['trip_pct_max']:+.2f}"
            bad = f" ({r['not_ok']} not ok)" if r["not_ok"] else ""
            lines.append(f"{combo:30s} {r['route']:16s} {r['fuel_corrected_J'] / 1e6:10.2f} "
                         f"{r['off_charge']:4d} {r['trip_long']:5d} {worst:>7s}{bad}")
        lines.append(f"{combo:30s} {'all':16s} "
                     f"{sum(r['fuel_corrected_J'] for r in rows) / 1e6:10.2f} "
                     f"{sum(r['off_charge'] for r in rows):4d} "
                     f"{sum(r['trip_long'] for r in rows):5d}")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--strategy", required=True, help="the strategy whose options are tried")
    ap.add_argument("--set", action="append", default=[], metavar="NAME=V1,V2",
                    help="an option and its values (repeatable; the product is tried)")
    ap.add_argument("--routes", default=",".join(DEFAULT_ROUTES),
                    help="comma-separated route files or bundled names")
    ap.add_argument("--masses", default="20000,30000,40000", help="masses in kg")
    ap.add_argument("--batteries", default="2,4,8", help="battery sizes in MJ")
    ap.add_argument("--vehicle", default="reference_truck", help="vehicle name or TOML file")
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    args = ap.parse_args(argv)

    def compute():
        strategy = check_strategy(args.strategy)
        return run_grid(strategy, option_values(args.set, strategy),
                        comma_list(args.routes, "--routes"), _floats(args.masses, "masses"),
                        _floats(args.batteries, "batteries"), args.vehicle)

    return print_result("option_grid", compute, args.json, format_table)


if __name__ == "__main__":
    from jaxems.cli import script_main

    sys.exit(script_main("option_grid", main))
