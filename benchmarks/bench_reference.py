"""Speed-up of the jitted, vmapped planning pipeline over its NumPy reference (a benchmark).

    python benchmarks/bench_reference.py [--route LongHaul] [--batch 64] [--repeats 3]
                                         [--ref-repeats 3] [--single] [--stages] [--json]

The pipeline is iteration 0 of the multilevel strategy's planning: Level 3 prediction ->
Level 2 costate by bisection (40 halvings, charge sustaining, no battery limits, gears from
the constant engine speed w_pred) -> Level 1 Hamiltonian table over mode x gear per step and
the Viterbi DP with switching costs (no plant run).

- NumPy: `jaxems.reference.reference_plan` for ONE configuration (the first of the batch),
  float64, `ref_repeats` runs; wall_s is the median, stage_s the per-stage seconds of the
  median run (level3, level2, level1_table, viterbi).
- JAX: `jaxems.reference.kernel_plan` under `xla.jit(jax.vmap(...))` (jaxems' jit, as the
  library compiles; `jax.jit` before 2026-11-24) over `batch` vehicle
  configurations (masses 15-40 t x batteries 1-8 MJ, a grid cycled to the batch), float32
  (with 64-bit types off, as sweeps run) and float64. The first call compiles (compile_s =
  first call minus the median), then `repeats` timed calls: median_s, configs_per_s =
  batch / median_s, and speedup = NumPy wall_s / (median_s / batch), the NumPy time of one
  configuration over the JAX time per configuration.
- --single: also one configuration jitted without vmap (jax.<precision>.single: median_s,
  configs_per_s, speedup); --stages: also each stage alone, vmapped over the batch (jax.<precision>.
  stages_s: level3, level2, level1 medians; level1 = Hamiltonian table + switching costs +
  Viterbi). Each adds its compilations to the run time.
- agreement: the float64 plan of the first configuration against the reference (relative fuel
  difference, costate difference, fraction of steps with the same mode and gear), and the
  float32 fuel against float64 over the batch.

With --json, one object on stdout:

    {"route", "batch", "n_steps", "numpy": {"wall_s", "wall_s_all", "stage_s",
     "configs_per_s"}, "jax": {"float32": {"median_s", "times_s", "compile_s",
     "configs_per_s", "speedup"[, "single", "stages_s"]}, "float64": {...}},
     "agreement": {...},
     "machine": {"cpus", "loadavg_before", "loadavg_after"}}

Timings are wall-clock on whatever else the machine runs: quote medians and the load average
reported with them, and compare ratios measured in one run.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time

import jax
import numpy as np


def vehicles(n: int):
    """n configurations: masses 15-40 t x battery sizes 1-8 MJ, an 8 x 8 grid walked so that
    every 8 consecutive members have different masses and batteries (cycled beyond 64). The
    first (15 t, 1 MJ) is the configuration the NumPy reference runs."""
    from jaxems.params import load_vehicle

    base = load_vehicle()
    masses, batts = np.linspace(15e3, 40e3, 8), np.linspace(1e6, 8e6, 8)
    return [base.replace(mass=masses[i % 8], E_b_max=batts[(i // 8 + i) % 8])
            for i in range(n)]


def _cast(tree, dtype):
    """Floating leaves to dtype (booleans and integers kept)."""
    def one(a):
        a = np.asarray(a)
        return a.astype(dtype) if np.issubdtype(a.dtype, np.floating) else a

    return jax.tree_util.tree_map(one, tree)


def _timed(f, args, repeats):
    """Call f(*args) once (compiles), then `repeats` times: (output, timing dict)."""
    t0 = time.perf_counter()
    out = jax.block_until_ready(f(*args))
    first = time.perf_counter() - t0
    times = []
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        out = jax.block_until_ready(f(*args))
        times.append(time.perf_counter() - t0)
    med = statistics.median(times)
    return out, {"median_s": med, "times_s": times, "compile_s": max(first - med, 0.0)}


def _time_jax(route, vps, vp0, params, n_steps, dtype, repeats, single, stages):
    from jaxems import reference as ref
    from jaxems import xla

    route, vps, vp0, params = (_cast(x, dtype) for x in (route, vps, vp0, params))
    plan = lambda r, vp, p: ref.kernel_plan(r, vp, p, dt=1.0, n_steps=n_steps)  # noqa: E731
    out, t = _timed(xla.jit(jax.vmap(plan, in_axes=(None, 0, None))), (route, vps, params),
                    repeats)
    if single:  # one configuration, jitted without vmap
        _, ts = _timed(xla.jit(plan), (route, vp0, params), repeats)
        t["single"] = {**ts, "configs_per_s": 1.0 / ts["median_s"]}
    if stages:  # each stage on its own, vmapped over the batch
        l3 = xla.jit(jax.vmap(lambda r, vp: ref.kernel_level3(r, vp, dt=1.0, n_steps=n_steps),
                              in_axes=(None, 0)))
        l2 = xla.jit(jax.vmap(lambda vp, pred: ref.kernel_level2(vp, pred, dt=1.0).lam0))
        l1 = xla.jit(jax.vmap(lambda vp, pred, lam, p: ref.kernel_level1(vp, pred, lam, p, dt=1.0),
                              in_axes=(0, 0, 0, None)))
        pred, t3 = _timed(l3, (route, vps), repeats)
        lam, t2 = _timed(l2, (vps, pred), repeats)
        _, t1 = _timed(l1, (vps, pred, lam, params), repeats)
        t["stages_s"] = {"level3": t3["median_s"], "level2": t2["median_s"],
                         "level1": t1["median_s"]}
    return out, t


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--route", default="LongHaul")
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--repeats", type=int, default=3, help="timed JAX calls (after compiling)")
    ap.add_argument("--ref-repeats", type=int, default=3, help="NumPy reference runs")
    ap.add_argument("--single", action="store_true",
                    help="also time one configuration jitted without vmap")
    ap.add_argument("--stages", action="store_true",
                    help="also time Level 3, Level 2 and Level 1 each on its own (vmapped)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    if args.batch < 1:
        ap.error("--batch must be >= 1")
    jax.config.update("jax_enable_x64", True)
    from jaxems.io import load_route
    from jaxems.params import stack_vehicles
    from jaxems.reference import compare_plans, reference_plan
    from jaxems.strategies import steps_for_batch
    from jaxems.switching import SwitchCostParams

    load0 = os.getloadavg()
    route = load_route(args.route)
    vp_list = vehicles(args.batch)
    vps = stack_vehicles(vp_list)
    params = SwitchCostParams()
    n_steps = steps_for_batch(route, vps)
    log = lambda *a: print(*a, file=sys.stderr, flush=True)  # noqa: E731
    out = {"route": args.route, "batch": args.batch, "n_steps": n_steps, "jax": {}}

    runs = []
    for _ in range(max(1, args.ref_repeats)):
        t0 = time.perf_counter()
        plan = reference_plan(route, vp_list[0], dt=1.0, n_steps=n_steps, params=params)
        runs.append((time.perf_counter() - t0, plan))
    walls = [w for w, _ in runs]
    wall = statistics.median(walls)
    stage = sorted(runs, key=lambda x: x[0])[len(runs) // 2][1].stage_s
    ref_plan = runs[0][1]
    out["numpy"] = {"wall_s": wall, "wall_s_all": walls, "stage_s": stage,
                    "configs_per_s": 1.0 / wall}
    log(f"numpy     {1.0 / wall:10.3f} configs/s  median {wall:8.2f} s  stages "
        + " ".join(f"{k} {v:.2f}" for k, v in stage.items()))

    results = {}
    for name in ("float32", "float64"):
        dtype = np.float32 if name == "float32" else np.float64
        with jax.enable_x64(name == "float64"):
            res, t = _time_jax(route, vps, vp_list[0], params, n_steps, dtype, args.repeats,
                               args.single, args.stages)
        per_config = t["median_s"] / args.batch
        t["configs_per_s"] = args.batch / t["median_s"]
        t["speedup"] = wall / per_config
        if "single" in t:
            t["single"]["speedup"] = wall / t["single"]["median_s"]
        out["jax"][name] = t
        results[name] = res
        log(f"jax {name} {t['configs_per_s']:10.2f} configs/s  median {t['median_s']:8.3f} s  "
            f"compile {t['compile_s']:6.1f} s  speed-up {t['speedup']:8.1f}x")
        if "single" in t:
            log(f"  single (no vmap) {t['single']['configs_per_s']:8.2f} configs/s  speed-up "
                f"{t['single']['speedup']:8.1f}x")
        if "stages_s" in t:
            log("  stages (vmapped) " + " ".join(f"{k} {v:.3f} s" for k, v in
                                                 t["stages_s"].items()))

    r64 = jax.tree_util.tree_map(lambda a: np.asarray(a)[0], results["float64"])
    agree = compare_plans(ref_plan, r64)
    f32 = np.asarray(results["float32"].fuel_J, np.float64)
    f64 = np.asarray(results["float64"].fuel_J)
    agree["fuel32_vs_64_rel_max"] = float(np.max(np.abs(f32 - f64) / np.abs(f64)))
    agree["fuel32_vs_64_rel_median"] = float(np.median(np.abs(f32 - f64) / np.abs(f64)))
    out["agreement"] = agree
    out["machine"] = {"cpus": os.cpu_count(), "loadavg_before": load0,
                      "loadavg_after": os.getloadavg()}
    log("agreement " + " ".join(f"{k} {v:.3g}" for k, v in agree.items()))
    if args.json:
        print(json.dumps(out))
    return 0


if __name__ == "__main__":
    from jaxems.cli import script_main

    raise SystemExit(script_main("bench_reference", main))
