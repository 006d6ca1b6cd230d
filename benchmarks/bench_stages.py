"""Where multilevel's time goes: each stage of one iteration timed apart (a benchmark).

    python benchmarks/bench_stages.py [--route LongHaul] [--batch 4] [--repeats 5]
                                      [--precision float32] [--json]

`batch` vehicle configurations (the grid of `bench_sweep.vehicles`: masses 15-40 t x battery
sizes 1-8 MJ) are vmapped on one device, as `simulate_batch` runs one chunk. Each stage of the
multilevel iteration (`strategies._iterate`, iteration 0, with the strategy's default options)
is jitted on its own, on the outputs of the stage before it:

- level3: the velocity prediction (`strategies.level3`);
- level2: the costate by bisection with the battery's limits (`battery.costate_kernel`);
- level1_tables: one Level 1 DP's inputs, the Hamiltonian of every mode and gear and the
  switching costs (`level1.dp_inputs`); level1_hamiltonian: the Hamiltonian table alone;
- level1_viterbi: one Level 1 DP's recursion and backward pass (`level1.solve_dp`);
  level1_viterbi_cost_only: the forward recursion without the argmin (what the back-pointers
  add is the difference);
- level1_sustaining: the Level 1 that keeps Level 2's battery plan (`sustaining_level1`),
  `sustaining_dps` full-route DPs;
- plant: the plan (`make_plan`) run on the plant (`plant.run_plant`);
- repredict_level3: Level 3 again with the plan's engine speeds;
- multilevel: the whole strategy (`Options().n_iter` iterations), for comparison with the sum of
  the stages per iteration.

Figures are wall-clock milliseconds per configuration: median and minimum of `repeats` calls
after the first (which compiles; compile_s is its wall time). The machine is shared: compare
stages measured in one run.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from jaxems.cli import positive_int

sys.path.insert(0, str(Path(__file__).resolve().parent))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--route", default="LongHaul")
    ap.add_argument("--batch", type=positive_int, default=4)
    ap.add_argument("--repeats", type=positive_int, default=5)
    ap.add_argument("--precision", choices=("float32", "float64"), default="float32")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)

    import jax

    if args.precision == "float64":
        jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    from bench_sweep import vehicles

    from jaxems import plan as pn
    from jaxems import plant as pl
    from jaxems import strategies as S
    from jaxems import switching as sw
    from jaxems import xla
    from jaxems.io import load_route
    from jaxems.levels import battery as l2
    from jaxems.levels import level1 as l1
    from jaxems.levels.powersplit import hamiltonian_table

    B, dt = args.batch, 1.0
    route = load_route(args.route)
    vps = vehicles(B, np.dtype(args.precision))
    opts = S.resolve_options(S.Options(), vps)
    n_steps = S.steps_for_batch(route, vps, dt, "multilevel", opts)
    params = sw.SwitchCostParams()
    out = {"route": args.route, "batch": B, "precision": args.precision, "n_steps": n_steps,
           "repeats": args.repeats, "device": str(jax.devices()[0]), "stages": {}}

    def timed(name, f, *a):
        f = xla.jit(f)
        t = time.perf_counter()
        res = jax.block_until_ready(f(*a))
        compile_s = time.perf_counter() - t
        ts = []
        for _ in range(args.repeats):
            t = time.perf_counter()
            res = jax.block_until_ready(f(*a))
            ts.append(time.perf_counter() - t)
        out["stages"][name] = {"ms_per_config": 1e3 * float(np.median(ts)) / B,
                               "min_ms_per_config": 1e3 * float(np.min(ts)) / B,
                               "compile_s": compile_s}
        if not args.json:
            print(f"{name:26s} {out['stages'][name]['ms_per_config']:9.2f} ms/config "
                  f"(min {out['stages'][name]['min_ms_per_config']:.2f}, "
                  f"first call {compile_s:.1f} s)", flush=True)
        return res

    v = jax.vmap
    pred = timed("level3", v(lambda vp: S.level3(route, vp, dt, n_steps)), vps)
    w0 = v(lambda p, vp: jnp.full_like(p.v, vp.w_pred))(pred, vps)
    c2 = timed("level2", v(lambda vp, p, w: l2.costate_kernel(
        vp, p.P_d, p.v, w, p.mask, dt, max_pieces=opts.l2_pieces)), vps, pred, w0)

    lam, pieces = xla.jit(v(lambda vp, p, c: S.level1_targets(vp, p, c, pn.no_drift(p), opts)))(
        vps, pred, c2)
    trac = xla.jit(v(lambda vp, p: l1.traction_table(vp, p.v, p.grade, params)))(vps, pred)

    def tables(vp, p, lam_t, tr):
        return l1.dp_inputs(vp, p.P_d, p.v, p.grade, lam_t, dt, params, tr)

    tb = timed("level1_tables", v(tables), vps, pred, lam, trac)
    timed("level1_hamiltonian", v(lambda vp, p, lam_t: hamiltonian_table(
        vp, p.P_d, p.v, lam_t).H), vps, pred, lam)

    def viterbi(vp, t, p):
        S_ = t.stage.shape[1]
        m0, g0 = pn.init_state(p)
        init = l1._init_cost(m0, g0, S_, S_ // 4, t.stage.dtype)
        return l1.solve_dp(vp.dt_M, vp.dt_G, t.stage, t.xs, t.consts, t.dconsts, init, p.mask,
                           fast=opts.same_open_time)

    timed("level1_viterbi", v(lambda *a: viterbi(*a)[:2]), vps, tb, pred)
    timed("level1_viterbi_cost_only", v(lambda *a: viterbi(*a).cost), vps, tb, pred)
    r1, lam1 = timed("level1_sustaining", v(lambda vp, p, lam_t, pc: pn.sustaining_level1(
        vp, p, lam_t, dt, params, *pc, fast=opts.same_open_time)), vps, pred, lam, pieces)
    out["sustaining_dps"] = pn.sustaining_dps(int(pred.v.shape[-1]))
    n_plant = S.plant_steps(n_steps, opts)

    def plant(vp, p, r, lam_t, pc):
        plan = pn.make_plan(vp, r.mode, r.gear, r.P_b, lam_t, p, dt, opts, pc)
        return S._run_plan(vp, pl.make_track(route, p, opts.end_cap), p, plan, n_plant,
                           dt).final.tot.fuel

    timed("plant", v(plant), vps, pred, r1, lam1, pieces)
    timed("repredict_level3", v(lambda vp, p, r: S.repredict_level3(
        route, vp, dt, n_steps, p, r.mode, r.w)), vps, pred, r1)
    timed("multilevel", v(lambda vp: S.run_multilevel(route, vp, dt, n_steps, opts,
                                                      params).metrics.fuel_J), vps)
    st = out["stages"]
    per_iter = sum(st[k]["ms_per_config"] for k in
                   ("level2", "level1_sustaining", "plant", "repredict_level3"))
    out["n_iter"] = opts.n_iter
    out["stages_sum_ms_per_config"] = st["level3"]["ms_per_config"] + opts.n_iter * per_iter
    if args.json:
        print(json.dumps(out))
    else:
        print(f"sustaining Level 1: {out['sustaining_dps']} DPs; level3 + {opts.n_iter} x "
              f"(level2 + level1_sustaining + plant + repredict_level3) = "
              f"{out['stages_sum_ms_per_config']:.1f} ms/config")
    return 0


if __name__ == "__main__":
    from jaxems.cli import script_main

    raise SystemExit(script_main("bench_stages", main))
