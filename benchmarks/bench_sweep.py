"""Fleet throughput of the strategies: configurations per second on one route (a benchmark).

    python benchmarks/bench_sweep.py [--route LongHaul] [--batch 1024] [--strategies ...]
                                     [--repeats 3] [--precision float32] [--json]

For each strategy: one `simulate_batch` call on `batch` vehicle configurations (masses and
battery sizes spread over a grid) compiles (reported as compile_s: the first call's wall time
minus a timed second call), then `repeats` timed calls give the median wall time and
configs_per_s = batch / median. peak_rss_MB is the process's peak resident memory after the
strategy (it only grows, so later strategies include earlier ones). With --json one object:

    {"route": .., "batch": .., "precision": .., "strategies": {NAME: {"configs_per_s": ..,
     "compile_s": .., "peak_rss_MB": .., "median_s": ..}}}

Timings are wall-clock on a shared machine: compare ratios measured in one run.
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import sys
import time

import jax
import numpy as np


def vehicles(n: int, dtype):
    """n configurations: masses 15-40 t x battery sizes 1-8 MJ (a grid, cycled to n)."""
    from jaxems.params import load_vehicle, stack_vehicles

    base = load_vehicle()
    masses = np.linspace(15e3, 40e3, 8)
    batts = np.linspace(1e6, 8e6, 8)
    pts = [(m, b) for m in masses for b in batts]
    vps = [base.replace(mass=pts[i % len(pts)][0], E_b_max=pts[i % len(pts)][1])
           for i in range(n)]
    stack = stack_vehicles(vps)
    return jax.tree_util.tree_map(lambda a: np.asarray(a, dtype), stack)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--route", default="LongHaul")
    ap.add_argument("--batch", type=int, default=1024)
    ap.add_argument("--strategies", default="conventional,baseline,multilevel,multilevel-mpc")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--precision", choices=("float32", "float64"), default="float32")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    x64 = args.precision == "float64"
    jax.config.update("jax_enable_x64", x64)
    from jaxems.io import load_route
    from jaxems.strategies import simulate_batch, steps_for_batch

    dtype = np.float64 if x64 else np.float32
    route = load_route(args.route)
    vps = vehicles(args.batch, dtype)
    n_steps = steps_for_batch(route, vps)
    out = {"route": args.route, "batch": args.batch, "precision": args.precision,
           "n_steps": n_steps, "strategies": {}}
    for name in args.strategies.split(","):
        t0 = time.perf_counter()
        simulate_batch(route, vps, name, n_steps=n_steps)
        first = time.perf_counter() - t0
        times = []
        for _ in range(max(1, args.repeats)):
            t0 = time.perf_counter()
            simulate_batch(route, vps, name, n_steps=n_steps)
            times.append(time.perf_counter() - t0)
        med = statistics.median(times)
        rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
        out["strategies"][name] = {"configs_per_s": args.batch / med,
                                   "compile_s": max(first - med, 0.0), "median_s": med,
                                   "peak_rss_MB": rss}
        print(f"{name:15s} {args.batch / med:10.2f} configs/s  median {med:8.2f} s  "
              f"compile {max(first - med, 0.0):7.1f} s  peak RSS {rss:8.0f} MB",
              file=sys.stderr, flush=True)
    if args.json:
        print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
