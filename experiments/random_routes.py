"""Beyond the bundled routes: the strategies on random short routes, against the end-to-end
checks (charge within 1 % of the battery, trip time within 1 % of Level 3, the hybrids below
the conventional truck's fuel).

Each route launches from a stop, runs 1-4 sections of random gradient (within
+-``--grade-max`` %) and speed limit (30, 50, 70 or 90 km/h) over 300-1000 m, perhaps stops
10 s between two of them, and stops at its end; each has its own mass (uniform in
``--masses``), 4 MJ at half charge. The routes share one shape (512 nodes, 10 m cells), so
each strategy compiles once or twice (256 or 512 steps). Float64.

    .venv/bin/python experiments/random_routes.py [--n 60] [--seed 1] [--grade-max 8]
        [--masses 15000,40000] [--strategies conventional,baseline,multilevel] [--json]

`--json` prints one JSON object ``{"rows": [...], "summary": {...}, ...}`` on stdout; progress
goes to stderr. The property test `test_any_route_runs_to_its_end_with_its_energy_balanced`
(tests/test_strategies.py) draws its routes with `random_rows` too.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np
from jax import config

config.update("jax_enable_x64", True)

from jaxems.cli import comma_list, number, print_result, whole_number  # noqa: E402
from jaxems.params import check_vehicle, load_vehicle, with_overrides  # noqa: E402
from jaxems.report import CHARGE_SHARE, off_charge, trip_vs_level3_pct  # noqa: E402
from jaxems.route import Route, Row, route_from_rows  # noqa: E402
from jaxems.strategies import check_strategy, simulate  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from charge_grid import _floats  # noqa: E402
from table7 import _num  # noqa: E402

DEFAULT_STRATEGIES = ("conventional", "baseline", "multilevel")
SPEEDS_KMH = (30, 50, 70, 90)


class NumpyPick(NamedTuple):
    """What `random_rows` draws, from a NumPy generator (the property test's `HypothesisPick`
    draws the same with hypothesis)."""

    rng: np.random.Generator

    def real(self, lo: float, hi: float) -> float:
        return float(self.rng.uniform(lo, hi))

    def whole(self, lo: int, hi: int) -> int:  # lo..hi, both included
        return int(self.rng.integers(lo, hi + 1))

    def one_of(self, seq):
        return seq[int(self.rng.integers(len(seq)))]

    def distinct(self, n: int, lo: int, hi: int) -> list[int]:  # sorted, lo..hi
        return sorted(int(x) for x in self.rng.choice(np.arange(lo, hi + 1), n, replace=False))


def random_rows(pick, grade_max: float = 8.0) -> list[tuple]:
    """(s m, v km/h, grade %, stop s) rows of one random route (see the module docstring);
    pick: draws real(lo, hi), whole(lo, hi), one_of(seq) and distinct(n, lo, hi)."""
    L = round(pick.real(300.0, 1000.0), 1)
    n = pick.whole(1, 4)
    starts = [0.001] + [round(c * L / 100.0, 1) for c in pick.distinct(n - 1, 5, 95)]
    stop_at = pick.whole(0, n - 1)  # 0: no stop halfway
    rows = [(0.0, 0.0, 0.0, 5.0)]
    for i, s0 in enumerate(starts):
        v = float(pick.one_of(SPEEDS_KMH))
        g = round(pick.real(-grade_max, grade_max), 1)
        if i and i == stop_at:
            rows += [(s0, 0.0, g, 10.0), (s0 + 0.001, v, g, 0.0)]
        else:
            rows.append((s0, v, g, 0.0))
    rows.append((L, 0.0, 0.0, 2.0))
    return rows


def route_of(rows) -> Route:
    """The `Route` of `random_rows`' rows: 10 m cells, padded to 512 nodes (the short track's
    shape)."""
    return route_from_rows([Row(*r, line=i + 2) for i, r in enumerate(rows)], ds=10.0,
                           bucket=512)


def run_routes(n: int = 60, seed: int = 1, grade_max: float = 8.0,
               masses=(15000.0, 40000.0), strategies=DEFAULT_STRATEGIES,
               vehicle: str = "reference_truck") -> dict:
    """Every strategy on n random routes: {"rows": [...], "summary": {strategy: {...}}, ...};
    bad input raises ValueError (naming the field) before anything runs."""
    for s in strategies:
        check_strategy(s)
    if "conventional" not in strategies:
        raise ValueError("--strategies: conventional is the reference of the fuel ratios")
    if n < 1:
        raise ValueError(f"--n: at least one route (got {n})")
    if not 0.0 <= grade_max <= 30.0:
        raise ValueError(f"--grade-max: a gradient in % from 0 to 30 (got {grade_max:g})")
    if len(masses) != 2 or not 0 < masses[0] <= masses[1]:
        raise ValueError(f"--masses: two masses in kg, the least first (got {masses})")
    base = load_vehicle(vehicle)
    pick = NumpyPick(np.random.default_rng(seed))
    rows = []
    for k in range(n):
        spec = random_rows(pick, grade_max)
        mass = round(pick.real(*masses), 1)
        route = route_of(spec)
        vp = check_vehicle(with_overrides(base, mass_kg=mass))
        size = float(vp.E_b_max)
        here = {}
        for strategy in strategies:
            t = time.perf_counter()
            r = simulate(route, vp, strategy)
            t3 = float(r.prediction.trip_time)
            here[strategy] = row = {
                "route": k, "mass_kg": mass, "rows": [list(x) for x in spec],
                "strategy": strategy, "status": str(r["status"]),
                "fuel_corrected_J": _num(r["fuel_corrected_J"]),
                "delta_Eb_pct": _num(100 * r["delta_Eb_J"] / size),
                "sustained": not off_charge(r["delta_Eb_J"], size),
                "trip_time_s": _num(r["trip_time_s"]), "level3_trip_time_s": _num(t3),
                "trip_pct": _num(trip_vs_level3_pct(r["trip_time_s"], t3)),
            }
            print(f"random_routes: route {k} {mass:7.0f} kg {strategy:15s} {row['status']} "
                  f"{row['delta_Eb_pct']:+7.2f} % ({time.perf_counter() - t:.1f} s)",
                  file=sys.stderr, flush=True)
        conv = here["conventional"]["fuel_corrected_J"]
        for row in here.values():
            row["fuel_ratio"] = _num(row["fuel_corrected_J"] / conv)
        rows += here.values()
    return {"n": n, "seed": seed, "grade_max_pct": grade_max, "masses_kg": list(masses),
            "vehicle": vehicle, "target_pct": 100 * CHARGE_SHARE, "rows": rows,
            "summary": summarise(rows)}


def summarise(rows: list[dict]) -> dict:
    """Per strategy: runs, runs ok, fuel ratios to the conventional truck (range, how many
    above 1), charge (how many off by more than the target, the largest miss in %) and trip
    time against Level 3 (range in %, how many beyond 1 %, the end-to-end issue's target;
    the plant's trip ends where its last step reaches the route's end)."""
    out = {}
    for strategy in dict.fromkeys(r["strategy"] for r in rows):
        rs = [r for r in rows if r["strategy"] == strategy]
        ratio = [r["fuel_ratio"] for r in rs]
        trip = [r["trip_pct"] for r in rs]
        out[strategy] = {
            "runs": len(rs), "ok": sum(r["status"] == "ok" for r in rs),
            "fuel_ratio_min": min(ratio), "fuel_ratio_max": max(ratio),
            "fuel_above_conventional": sum(x > 1.0 for x in ratio),
            "off_charge": sum(not r["sustained"] for r in rs),
            "max_abs_delta_Eb_pct": max(abs(r["delta_Eb_pct"]) for r in rs),
            "trip_pct_min": min(trip), "trip_pct_max": max(trip),
            "trip_beyond_target": sum(
                abs(r["trip_time_s"] - r["level3_trip_time_s"])
                > 0.01 * r["level3_trip_time_s"] for r in rs),
        }
    return out


def format_table(out: dict) -> str:
    head = (f"{'strategy':15s} {'runs':>4s} {'ok':>4s} {'fuel / conventional':>19s} "
            f"{'above':>5s} {'off charge':>10s} {'max |dE_b| %':>12s} {'trip vs L3 %':>14s} "
            f"{'beyond':>6s}")
    lines = [f"{out['n']} random routes (seed {out['seed']}, gradients within "
             f"{out['grade_max_pct']:g} %, {out['masses_kg'][0]:.0f}-{out['masses_kg'][1]:.0f} "
             f"kg); corrected fuel against the conventional truck's (above: how many > 1); "
             f"off charge: |delta E_b| above {out['target_pct']:g} % of the battery; trip "
             f"beyond: over 1 % from Level 3's",
             head, "-" * len(head)]
    for strategy, s in out["summary"].items():
        lines.append(
            f"{strategy:15s} {s['runs']:4d} {s['ok']:4d} "
            f"{s['fuel_ratio_min']:9.4f}-{s['fuel_ratio_max']:<9.4f} "
            f"{s['fuel_above_conventional']:5d} {s['off_charge']:10d} "
            f"{s['max_abs_delta_Eb_pct']:12.2f} "
            f"{s['trip_pct_min']:+6.2f}..{s['trip_pct_max']:+6.2f} "
            f"{s['trip_beyond_target']:6d}")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=whole_number, default=60, help="number of routes (60)")
    ap.add_argument("--seed", type=whole_number, default=1, help="random seed (1)")
    ap.add_argument("--grade-max", type=number, default=8.0, help="largest |gradient| in %% (8)")
    ap.add_argument("--masses", default="15000,40000", help="mass range in kg (15000,40000)")
    ap.add_argument("--strategies", default=",".join(DEFAULT_STRATEGIES),
                    help="comma-separated strategies, conventional among them")
    ap.add_argument("--vehicle", default="reference_truck", help="vehicle name or TOML file")
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    args = ap.parse_args(argv)

    def compute():
        strategies = comma_list(args.strategies, "--strategies")
        return run_routes(args.n, args.seed, args.grade_max, _floats(args.masses, "masses"),
                          strategies, args.vehicle)

    return print_result("random_routes", compute, args.json, format_table)


if __name__ == "__main__":
    from jaxems.cli import script_main

    sys.exit(script_main("random_routes", main))
