"""Charge sustaining away from the tables' vehicle: the battery balance of the hybrid strategies
over starting charges and masses on one route.

Tables 7 and 8 use one vehicle (25 / 20 t, 4 MJ, starting at half charge). This script runs
each strategy over a grid of starting charges (`soc0`) and masses and gives, per run, delta E_b
in % of the battery (end minus start; the issue's target is within 1 %), the corrected fuel
J + lambda_b delta E_b and the first costate. A new starting charge or mass is an array leaf:
each strategy compiles once. Float64.

    .venv/bin/python experiments/charge_grid.py [--route short_track] [--masses 25000]
        [--socs 0.1,0.3,0.5,0.7,0.9] [--strategies baseline,multilevel,multilevel-mpc,dp-bound]
        [--json]

`--json` prints one JSON object ``{"rows": [...], ...}`` on stdout; progress goes to stderr.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from jax import config

config.update("jax_enable_x64", True)

from jaxems.cli import comma_list, print_result  # noqa: E402
from jaxems.io import load_route  # noqa: E402
from jaxems.params import check_vehicle, load_vehicle, with_overrides  # noqa: E402
from jaxems.report import CHARGE_SHARE, off_charge  # noqa: E402
from jaxems.strategies import check_strategy, simulate  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from table7 import _num  # noqa: E402  (as Table 7 reads lists and writes numbers)

DEFAULT_STRATEGIES = ("baseline", "multilevel", "multilevel-mpc", "dp-bound")
TARGET_PCT = 100 * CHARGE_SHARE  # the end-to-end check: |delta E_b| within 1 % of the battery


def _floats(text: str, name: str) -> list[float]:
    try:
        vals = [float(x) for x in comma_list(text)]
    except ValueError:
        raise ValueError(f"--{name}: expected comma-separated numbers (got {text!r})") from None
    if not vals:
        raise ValueError(f"--{name}: expected at least one number")
    return vals


def run_grid(route: str = "short_track", masses=(25000.0,), socs=(0.1, 0.3, 0.5, 0.7, 0.9),
             strategies=DEFAULT_STRATEGIES, vehicle: str = "reference_truck") -> dict:
    """Every (strategy, mass, soc0) on the route: {"route", "rows": [...]}; bad input raises
    ValueError (naming the field) before anything runs."""
    for s in strategies:
        check_strategy(s)
    rt = load_route(route)
    base = load_vehicle(vehicle)
    vps = [(m, s, check_vehicle(with_overrides(base, mass_kg=m).replace(soc0=s)))
           for m in masses for s in socs]
    rows = []
    for strategy in strategies:
        for m, soc, vp in vps:
            t = time.perf_counter()
            r = simulate(rt, vp, strategy)
            size = float(vp.E_b_max)
            rows.append({
                "strategy": strategy, "mass_kg": m, "soc0": soc, "fuel_J": _num(r["fuel_J"]),
                "fuel_corrected_J": _num(r["fuel_corrected_J"]),
                "delta_Eb_J": _num(r["delta_Eb_J"]),
                "delta_Eb_pct": _num(100 * r["delta_Eb_J"] / size),
                "lambda_b": _num(r["lambda_b"]), "status": str(r["status"]),
                "sustained": not off_charge(r["delta_Eb_J"], size),
            })
            print(f"charge_grid: {strategy:15s} {m:8.0f} kg soc0 {soc:.2f} "
                  f"{rows[-1]['delta_Eb_pct']:+7.2f} % ({time.perf_counter() - t:.1f} s)",
                  file=sys.stderr, flush=True)
    return {"route": route, "vehicle": vehicle, "target_pct": TARGET_PCT, "rows": rows}


def format_table(out: dict) -> str:
    """One line per (strategy, mass): delta E_b % of the battery at each starting charge, and
    how many runs are within the target."""
    rows = out["rows"]
    socs = sorted({r["soc0"] for r in rows})
    head = f"{'strategy':15s} {'mass kg':>8s} " + " ".join(f"{'soc ' + format(s, '.2f'):>9s}"
                                                          for s in socs)
    lines = [f"{out['route']}: delta E_b (end - start) in % of the battery, by starting charge "
             f"(target within {out['target_pct']:g} %)", head, "-" * len(head)]
    keys = dict.fromkeys((r["strategy"], r["mass_kg"]) for r in rows)
    for strategy, m in keys:
        by = {r["soc0"]: r for r in rows if r["strategy"] == strategy and r["mass_kg"] == m}
        cells = " ".join(f"{by[s]['delta_Eb_pct']:+9.2f}" if s in by else f"{'-':>9s}"
                         for s in socs)
        lines.append(f"{strategy:15s} {m:8.0f} {cells}")
    n_ok = sum(r["sustained"] for r in rows)
    lines.append(f"within {out['target_pct']:g} %: {n_ok} of {len(rows)} runs")
    return "\n".join(lines)


def parser(doc: str, strategies) -> argparse.ArgumentParser:
    """The options this script shares with resolution.py: --route, --vehicle, --strategies
    (default: `strategies`), --json."""
    ap = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    ap.add_argument("--route", default="short_track", help="route file or bundled name")
    ap.add_argument("--vehicle", default="reference_truck", help="vehicle name or TOML file")
    ap.add_argument("--strategies", default=",".join(strategies),
                    help="comma-separated strategies")
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    return ap


def main(argv=None) -> int:
    ap = parser(__doc__, DEFAULT_STRATEGIES)
    ap.add_argument("--masses", default="25000", help="comma-separated masses in kg (25000)")
    ap.add_argument("--socs", default="0.1,0.3,0.5,0.7,0.9",
                    help="comma-separated starting charges, fractions of the battery")
    args = ap.parse_args(argv)

    def compute():
        strategies = comma_list(args.strategies, "--strategies")
        return run_grid(args.route, _floats(args.masses, "masses"), _floats(args.socs, "socs"),
                        strategies, args.vehicle)

    return print_result("charge_grid", compute, args.json, format_table)


if __name__ == "__main__":
    from jaxems.cli import script_main

    sys.exit(script_main("charge_grid", main))
