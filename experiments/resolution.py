"""How finely the end-to-end figures resolve: each strategy at a mass and a few kilograms more.

A run's corrected fuel is not a smooth function of the vehicle: Level 1's modes and gears, the
plant's protection and the battery's limits are discrete, and a few kilograms more can flip a
decision that moves the run by a percent or more. This script runs each strategy at the mass
plus small offsets (0, 5, 10, 20, 50, 100 kg by default), starting at half charge, and gives
per strategy the corrected fuel J + lambda_b delta E_b at each mass, its median and its spread
(max - min over the median), and the gaps the end-to-end checks ask about, mass by mass and as
medians: multilevel against dp-bound and multilevel-mpc against multilevel. Float64; a new mass
is an array leaf, so each strategy compiles once.

    .venv/bin/python experiments/resolution.py [--route short_track] [--mass 25000]
        [--offsets 0,5,10,20,50,100] [--strategies multilevel,dp-bound,multilevel-mpc]
        [--json]

`--json` prints one JSON object ``{"rows": [...], "strategies": {...}, "gaps": {...}}`` on
stdout; progress goes to stderr.
"""

from __future__ import annotations

import statistics
import sys
from pathlib import Path

from jax import config

config.update("jax_enable_x64", True)

from jaxems.cli import comma_list, print_result  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from charge_grid import _floats, parser, run_grid  # noqa: E402

DEFAULT_STRATEGIES = ("multilevel", "dp-bound", "multilevel-mpc")
DEFAULT_OFFSETS = (0.0, 5.0, 10.0, 20.0, 50.0, 100.0)
# the gaps of the end-to-end checks: (name, strategy, against)
GAPS = (("multilevel vs dp-bound", "multilevel", "dp-bound"),
        ("multilevel-mpc vs multilevel", "multilevel-mpc", "multilevel"))


def summarise(rows: list[dict], masses: list[float]) -> tuple[dict, dict]:
    """Per strategy {corrected fuel by mass, median, spread_pct}; per gap of GAPS whose two
    strategies ran {gap_pct by mass, median_pct, min_pct, max_pct} (100 (a / b - 1))."""
    fuel = {}
    for r in rows:
        fuel.setdefault(r["strategy"], {})[r["mass_kg"]] = r["fuel_corrected_J"]
    strategies = {}
    for s, by in fuel.items():
        v = [by[m] for m in masses]
        med = statistics.median(v)
        strategies[s] = {"fuel_corrected_J": v, "median_J": med,
                         "spread_pct": 100 * (max(v) - min(v)) / med}
    gaps = {}
    for name, a, b in GAPS:
        if a in fuel and b in fuel:
            g = [100 * (fuel[a][m] / fuel[b][m] - 1) for m in masses]
            gaps[name] = {"gap_pct": g, "median_pct": statistics.median(g), "min_pct": min(g),
                          "max_pct": max(g)}
    return strategies, gaps


def run(route: str = "short_track", mass: float = 25000.0, offsets=DEFAULT_OFFSETS,
        strategies=DEFAULT_STRATEGIES, vehicle: str = "reference_truck") -> dict:
    """Every strategy at mass + each offset (kg), half charge: {"route", "masses", "rows",
    "strategies", "gaps"}; bad input raises ValueError naming the field."""
    masses = [mass + o for o in offsets]
    grid = run_grid(route, masses, (0.5,), strategies, vehicle)
    summary, gaps = summarise(grid["rows"], masses)
    return {"route": route, "vehicle": vehicle, "mass_kg": mass, "masses": masses,
            "rows": grid["rows"], "strategies": summary, "gaps": gaps}


def format_table(out: dict) -> str:
    masses = out["masses"]
    head = (f"{'':28s} " + " ".join(f"{'+' + format(m - out['mass_kg'], 'g') + ' kg':>9s}"
                                     for m in masses) + f" {'median':>9s} {'spread':>8s}")
    lines = [f"{out['route']}, {out['mass_kg']:g} kg and a few more: corrected fuel (MJ) and "
             f"the checks' gaps (%)", head, "-" * len(head)]
    for s, d in out["strategies"].items():
        cells = " ".join(f"{x / 1e6:9.3f}" for x in d["fuel_corrected_J"])
        lines.append(f"{s:28s} {cells} {d['median_J'] / 1e6:9.3f} {d['spread_pct']:7.2f}%")
    for name, d in out["gaps"].items():
        cells = " ".join(f"{x:+9.2f}" for x in d["gap_pct"])
        lines.append(f"{name:28s} {cells} {d['median_pct']:+9.2f}")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = parser(__doc__, DEFAULT_STRATEGIES)
    ap.add_argument("--mass", default="25000", help="the mass in kg (25000)")
    ap.add_argument("--offsets", default=",".join(format(o, "g") for o in DEFAULT_OFFSETS),
                    help="comma-separated kilograms added to the mass")
    args = ap.parse_args(argv)

    def compute():
        masses = _floats(args.mass, "mass")
        if len(masses) != 1:
            raise ValueError(f"--mass: expected one number (got {args.mass!r})")
        mass = masses[0]
        offsets = _floats(args.offsets, "offsets")
        if any(o < 0 for o in offsets) or len(set(offsets)) != len(offsets):
            raise ValueError(f"--offsets: expected distinct kilograms >= 0 (got {args.offsets!r})")
        return run(args.route, mass, offsets, comma_list(args.strategies), args.vehicle)

    return print_result("resolution", compute, args.json, format_table)


if __name__ == "__main__":
    sys.exit(main())
