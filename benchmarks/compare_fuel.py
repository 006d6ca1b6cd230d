"""Per-configuration fuel of two `bench_sweep.py --keep-fuel` runs, compared (a benchmark aid).

    python benchmarks/compare_fuel.py A.json B.json [--json]

For each strategy in both files: relative differences |a - b| / |b| of fuel_J for the
configurations both ran (configuration i is the vehicle grid's point i mod 64, so a larger
batch's first len(B) configurations are B's), their median, 90th percentile and largest, and
how many are within 1e-9 and 1e-6; and, where A repeats a configuration (batch > 64), the
largest spread of A's results for one configuration (a batch-position effect).
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

GRID = 64  # bench_sweep.vehicles cycles a grid of 64 configurations


def fuel(path: str) -> dict[str, np.ndarray]:
    with open(path) as f:
        data = json.load(f)
    out = {}
    for name, entry in data["strategies"].items():
        if "fuel_J" not in entry:
            raise SystemExit(f"compare_fuel: {path}: {name} has no fuel_J (run with --keep-fuel)")
        out[name] = np.asarray(entry["fuel_J"], float)
    return out


def compare(a: np.ndarray, b: np.ndarray) -> dict:
    n = min(len(a), len(b))
    r = np.abs(a[:n] - b[:n]) / np.abs(b[:n])
    out = {"n": int(n), "median": float(np.median(r)), "p90": float(np.quantile(r, 0.9)),
           "max": float(r.max()), "within_1e-9": int((r <= 1e-9).sum()),
           "within_1e-6": int((r <= 1e-6).sum())}
    if len(a) > GRID and len(a) % GRID == 0:
        grid = a.reshape(-1, GRID)
        out["max_spread_same_config_A"] = float((np.ptp(grid, axis=0) / grid.mean(axis=0)).max())
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("a")
    ap.add_argument("b")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    fa, fb = fuel(args.a), fuel(args.b)
    res = {name: compare(fa[name], fb[name]) for name in fa if name in fb}
    if not res:
        raise SystemExit("compare_fuel: no strategy in both files")
    if args.json:
        print(json.dumps(res))
    else:
        for name, r in res.items():
            print(f"{name:15s} n={r['n']:5d} median {r['median']:.1e} p90 {r['p90']:.1e} "
                  f"max {r['max']:.1e} within 1e-9: {r['within_1e-9']} 1e-6: "
                  f"{r['within_1e-6']}" + (f" spread in A {r['max_spread_same_config_A']:.1e}"
                                           if "max_spread_same_config_A" in r else ""))
    return 0


if __name__ == "__main__":
    from jaxems.cli import script_main

    raise SystemExit(script_main("compare_fuel", main))
