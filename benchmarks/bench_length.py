"""A strategy's time against route length, in one process (a benchmark).

    python benchmarks/bench_length.py [--strategies conventional] [--batch 8] [--lengths 1,4]
                                      [--repeats 3] [--json]

`batch` vehicle configurations (the grid of `bench_sweep.vehicles`) are vmapped on one device,
as `simulate_batch` runs one chunk, on LongHaul tiled `--lengths` times (`bench_sweep.tile_route`),
float32, with the strategy's code generator (`strategies.BATCH_ELEMENTAL`). Figures are wall
milliseconds per configuration and per unit of length (LongHaul's), the median of `repeats` calls
after the first (which compiles): linear growth keeps them equal. `bench_sweep.py --scaling`
measures the same over `simulate_batch` and both devices, one subprocess per point; this one is
quicker, and fits the small chunks where the plant's per-step work shows.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

from jaxems.cli import positive_int

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--strategies", default="conventional")
    ap.add_argument("--batch", type=positive_int, default=8)
    ap.add_argument("--lengths", type=lambda t: [positive_int(x) for x in t.split(",")],
                    default=[1, 4], help="comma-separated tilings of LongHaul (default 1,4)")
    ap.add_argument("--repeats", type=positive_int, default=3)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)

    import jax
    from bench_sweep import tile_route, vehicles

    from jaxems import strategies as st
    from jaxems import switching as sw
    from jaxems import xla
    from jaxems.io import load_route

    vps = vehicles(args.batch, np.float32)
    opts = st.resolve_options(st.Options(), vps)
    params = sw.checked_params(sw.SwitchCostParams(), np.float32)
    out = {"route": "LongHaul", "batch": args.batch, "precision": "float32",
           "repeats": args.repeats, "strategies": {}}
    for name in (st.check_strategy(x) for x in args.strategies.split(",")):
        points = {}
        for k in args.lengths:
            route = load_route("LongHaul")
            if k > 1:
                route = tile_route(route, k)
            n = st.steps_for_batch(route, vps, 1.0, name, opts)

            def fuel(v, route=route, n=n, name=name):
                return st._run(route, v, params, strategy=name, dt=1.0, n_steps=n,
                               opts=opts).metrics.fuel_J

            f = xla.jit(jax.vmap(fuel), elemental=st.BATCH_ELEMENTAL[name])
            jax.block_until_ready(f(vps))
            ts = []
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                jax.block_until_ready(f(vps))
                ts.append(time.perf_counter() - t0)
            ms = 1e3 * float(np.median(ts)) / args.batch / k
            points[str(k)] = {"n_steps": n, "ms_per_config_per_length": ms}
            print(f"{name:14s} x{k}: {ms:8.1f} ms per configuration per unit of length",
                  file=sys.stderr, flush=True)
        out["strategies"][name] = points
    if args.json:
        print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    from jaxems.cli import script_main

    raise SystemExit(script_main("bench_length", main))
