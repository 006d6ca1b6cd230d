"""Level 1 benchmark (not a test): Viterbi throughput and MPC latency, float32 on CPU.

    python benchmarks/bench_level1.py [--json] [--batch 1000] [--steps 4500] [--chunk 250]
                                      [--horizon 500] [--quick]

1. Viterbi throughput: the mode x gear DP (48 states) for a batch of configurations x steps,
   with the Level 1 switching costs (`relax_same_open_time`, the path `level1_full` takes when
   dt_M == dt_G; batch on the last axis), measured
   as (state x state x step) relaxations per second = 48 * 48 * steps * batch / time (the DP
   runs 37 x 37 of them with the open mode merged, `level1.merge_open`). The batch
   runs in chunks of --chunk configurations (the per-step traction-cost inputs of 1000 x 4500
   steps would need 2.6 GB at once); the time is the sum over chunks. For comparison on one
   chunk: the structured relaxation (any dt_M, dt_G), the dense (S, S) min-plus relaxation with
   a constant matrix per configuration, and `jax.vmap` of the one-configuration structured
   kernel (batch first).
2. MPC latency: one receding-horizon solve (`dp.viterbi_first`, first decision only) over a
   window of --horizon stages (the paper's 5 s at 100 Hz = 500) for one vehicle, from the
   window's tables, on the 37 states `solve_dp` runs (open mode merged; and on all 48 for
   comparison); and the same including the evaluation of the window's Hamiltonians and
   switching-cost inputs (`level1` tables). Median of repeated calls after compilation.
3. End to end: `level1_batch` (Hamiltonians + switching costs + DP + outputs) on 100
   configurations x steps.
Inputs are synthetic (random state costs with infeasible states, a route of random speeds and
grades, vehicles with varied inertias and lambda_b). With --json prints one JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxems import dp, stack_vehicles, xla
from jaxems.cli import positive_int
from jaxems import switching as sw
from jaxems.levels import level1 as l1
from jaxems.levels import powersplit as ps
from jaxems.params import load_vehicle

S = 48


def _timeit(f, *args, repeat=3):
    jax.block_until_ready(f(*args))  # compile
    ts = []
    for _ in range(repeat):
        t = time.perf_counter()
        jax.block_until_ready(f(*args))
        ts.append(time.perf_counter() - t)
    return float(np.median(ts)), float(min(ts))


def _vehicles(n):
    base = load_vehicle()
    rng = np.random.default_rng(1)
    return stack_vehicles(
        [
            base.replace(mass=rng.uniform(15e3, 40e3), I_e=rng.uniform(2, 4), I_m=rng.uniform(1, 2))
            for _ in range(n)
        ]
    )


def make_chunk(key, vps, T, B):
    """Synthetic batch-last DP inputs: stage (T, S, B), TransitionInputs, TransitionConsts."""
    k1, k2, k3, k4 = jax.random.split(key, 4)
    stage = jax.random.uniform(k1, (T, S, B), jnp.float32, 0.0, 2e5)
    stage = jnp.where(jax.random.uniform(k2, (T, S, B)) < 0.15, jnp.inf, stage)
    # the open mode's states cost the same in every gear, as the Hamiltonian's do
    # (`level1.merge_open` relies on it)
    o = ps.MO * (S // 4)
    stage = stage.at[:, o:].set(stage[:, o : o + 1])
    v = jax.random.uniform(k3, (T, B), jnp.float32, 3.0, 25.0)
    grade = jax.random.uniform(k4, (T, B), jnp.float32, -0.08, 0.08)
    lam = jnp.linspace(-2.4, -1.8, B, dtype=jnp.float32)
    prm = sw.SwitchCostParams()
    nv = jax.tree_util.tree_leaves(vps)[0].shape[0]
    vidx = jnp.arange(B) % nv
    vp_b = jax.tree_util.tree_map(lambda a: a[vidx], vps)
    per_step = jax.vmap(l1.transition_inputs, in_axes=(None, 0, 0, None, None))
    xs = jax.vmap(per_step, in_axes=(0, 1, 1, 0, None))(vp_b, v, grade, lam, prm)  # (B, T, ..)
    consts = jax.vmap(l1.transition_consts, in_axes=(0, None))(vp_b, prm.averaged)
    dconsts = jax.vmap(l1.dense_consts, in_axes=(0, None))(vp_b, prm.averaged)
    last = lambda a: jnp.moveaxis(a, 0, -1)  # noqa: E731
    xs = l1.TransitionInputs(scale=last(xs.scale), trac=last(xs.trac))
    consts = jax.tree_util.tree_map(last, consts)
    dconsts = jax.tree_util.tree_map(last, dconsts)
    return stage, xs, consts, dconsts, v, grade, lam, vp_b


@xla.jit
def dp_level1(stage, xs, dconsts):
    """The Level 1 DP as `level1_full` runs it for dt_M == dt_G (`relax_same_open_time` on
    the states with the open mode's merged, `merge_open`: 37 x 37 relaxations a step, counted
    below as the 48 x 48 they stand for)."""
    init = jnp.zeros(stage.shape[1:], stage.dtype)
    r = l1.solve_dp(None, None, stage, xs, None, dconsts, init, None, fast=True)
    return r.path, r.cost


@xla.jit
def dp_structured(stage, xs, consts):
    init = jnp.zeros(stage.shape[1:], stage.dtype)
    r = dp.viterbi(stage, l1.structured_transition(xs, consts), init)
    return r.path, r.cost


@xla.jit
def dp_dense(stage, C):
    init = jnp.zeros(stage.shape[1:], stage.dtype)
    r = dp.viterbi(stage, dp.dense_transition(C), init)
    return r.path, r.cost


def _one_config(stage, xs, consts):
    r = dp.viterbi(stage, l1.structured_transition(xs, consts), jnp.zeros(S, stage.dtype))
    return r.path, r.cost


dp_vmapped = xla.jit(jax.vmap(_one_config, in_axes=(-1, -1, -1), out_axes=-1))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--batch", type=positive_int, default=1000)
    ap.add_argument("--steps", type=positive_int, default=4500)
    ap.add_argument("--chunk", type=positive_int, default=250)
    ap.add_argument("--horizon", type=positive_int, default=500)
    ap.add_argument("--quick", action="store_true", help="small sizes (smoke run)")
    a = ap.parse_args(argv)
    if a.quick:
        a.batch, a.steps, a.chunk, a.horizon = 40, 300, 20, 100
    T, B, C = a.steps, a.batch, min(a.chunk, a.batch)
    n_chunks = -(-B // C)
    vps = _vehicles(10)
    out: dict = {
        "device": str(jax.devices()[0]),
        "cpu_count": os.cpu_count(),
        "dtype": "float32",
        "states": S,
        "steps": T,
        "batch": n_chunks * C,
        "chunk": C,
    }

    # 1. throughput, Level 1 relaxation (dt_M == dt_G), batch-last, chunked
    total = 0.0
    compile_t = None
    for i in range(n_chunks):
        stage, xs, consts, dconsts, *_ = make_chunk(jax.random.PRNGKey(i), vps, T, C)
        jax.block_until_ready((stage, xs, dconsts))
        if compile_t is None:
            t0 = time.perf_counter()
            jax.block_until_ready(dp_level1(stage, xs, dconsts))
            compile_t = time.perf_counter() - t0
        t0 = time.perf_counter()
        jax.block_until_ready(dp_level1(stage, xs, dconsts))
        total += time.perf_counter() - t0
    relax = S * S * T * n_chunks * C
    out["viterbi_level1"] = {
        "seconds": total,
        "relaxations_per_s": relax / total,
        "first_call_s": compile_t,
    }
    # comparisons on one chunk
    stage, xs, consts, dconsts, v, grade, lam, vp_b = make_chunk(jax.random.PRNGKey(0), vps, T, C)
    _, c_fast = dp_level1(stage, xs, dconsts)
    _, c_str = dp_structured(stage, xs, consts)
    out["fast_vs_structured_max_rel_cost_diff"] = float(
        jnp.max(jnp.abs(c_fast - c_str) / jnp.abs(c_str))
    )
    med, _ = _timeit(dp_structured, stage, xs, consts, repeat=1)
    out["viterbi_structured_any_open_times"] = {
        "seconds_per_chunk": med,
        "relaxations_per_s": S * S * T * C / med,
    }
    Cmat = jax.vmap(sw.switch_cost_matrix, in_axes=(0, 0, 0, 0, None))(
        vp_b, v[0], grade[0], lam, sw.SwitchCostParams()
    )
    Cmat = jnp.moveaxis(Cmat, 0, -1)  # (S, S, C): one constant matrix per configuration
    med, _ = _timeit(dp_dense, stage, Cmat, repeat=1)
    out["viterbi_dense_same_layout"] = {
        "seconds_per_chunk": med,
        "relaxations_per_s": S * S * T * C / med,
    }
    med, _ = _timeit(dp_vmapped, stage, xs, consts, repeat=1)
    out["viterbi_structured_vmap_batch_first"] = {
        "seconds_per_chunk": med,
        "relaxations_per_s": S * S * T * C / med,
    }

    # 2. MPC latency, one vehicle
    N = a.horizon
    vp1 = jax.tree_util.tree_map(lambda x: jnp.asarray(x[0], jnp.float32), vps)
    rng = np.random.default_rng(0)
    v1 = jnp.asarray(rng.uniform(15, 25, N), jnp.float32)
    g1 = jnp.asarray(rng.uniform(-0.05, 0.05, N), jnp.float32)
    Pd1 = jnp.asarray(rng.uniform(-1e5, 2e5, N), jnp.float32)
    prm = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float32), sw.SwitchCostParams())
    tb = xla.jit(l1.dp_inputs)(vp1, Pd1, v1, g1, jnp.float32(-2.0), jnp.float32(0.01), prm)
    init = jnp.where(jnp.arange(S) == 2 * 12 + 9, 0.0, jnp.inf).astype(jnp.float32)

    @xla.jit
    def mpc_solve(stage, xs, dconsts, init):  # as the strategies run it: open mode merged
        return l1.solve_dp(None, None, stage, xs, None, dconsts, init, None, first=True,
                           fast=True)

    @xla.jit
    def mpc_solve_48(stage, xs, dconsts, init):
        return dp.viterbi_first(stage, l1.fast_transition(xs, dconsts), init)

    @xla.jit
    def mpc_solve_structured(stage, xs, consts, init):
        return dp.viterbi_first(stage, l1.structured_transition(xs, consts), init)

    @xla.jit
    def mpc_solve_with_tables(vp, P_d, v, grade, lam, init):
        t = l1.dp_inputs(vp, P_d, v, grade, lam, jnp.float32(0.01), prm)
        return l1.solve_dp(
            vp.dt_M, vp.dt_G, t.stage, t.xs, t.consts, t.dconsts, init, None, first=True
        )

    def lat(f, *args, n=200):
        jax.block_until_ready(f(*args))
        ts = []
        for _ in range(n):
            t0 = time.perf_counter()
            jax.block_until_ready(f(*args))
            ts.append(time.perf_counter() - t0)
        return {
            "median_ms": 1e3 * float(np.median(ts)),
            "p90_ms": 1e3 * float(np.quantile(ts, 0.9)),
            "min_ms": 1e3 * float(min(ts)),
        }

    out["mpc_horizon"] = N
    out["mpc_dp_latency"] = lat(mpc_solve, tb.stage, tb.xs, tb.dconsts, init)
    out["mpc_dp_48_states_latency"] = lat(mpc_solve_48, tb.stage, tb.xs, tb.dconsts, init)
    out["mpc_dp_structured_latency"] = lat(mpc_solve_structured, tb.stage, tb.xs, tb.consts, init)
    out["mpc_dp_plus_hamiltonian_latency"] = lat(
        mpc_solve_with_tables, vp1, Pd1, v1, g1, jnp.float32(-2.0), init, n=50
    )

    # 3. end to end level1_batch on 100 configurations (10 routes x 5 vehicles x 2 lambda)
    R, V, L = (10, 5, 2) if not a.quick else (2, 2, 2)
    Pd = jnp.asarray(rng.uniform(-1e5, 2e5, (R, T)), jnp.float32)
    vv = jnp.asarray(rng.uniform(5, 25, (R, T)), jnp.float32)
    gg = jnp.asarray(rng.uniform(-0.05, 0.05, (R, T)), jnp.float32)
    mk = jnp.ones((R, T), bool)
    vps5 = jax.tree_util.tree_map(lambda x: jnp.asarray(x[:V], jnp.float32), vps)
    lams = jnp.asarray([-2.0, -2.2], jnp.float32)[:L]
    f = lambda *args: l1.level1_batch(*args).cost  # noqa: E731
    med, mn = _timeit(f, vps5, Pd, vv, gg, mk, lams, jnp.float32(1.0), 3, 5, prm, repeat=1)
    out["level1_batch_end_to_end"] = {
        "configs": R * V * L,
        "seconds": med,
        "config_steps_per_s": R * V * L * T / med,
        "equivalent_relaxations_per_s": S * S * R * V * L * T / med,
    }
    if a.json:
        print(json.dumps(out))
    else:
        for k, val in out.items():
            print(f"{k}: {val}")
    return 0


if __name__ == "__main__":
    from jaxems.cli import script_main

    raise SystemExit(script_main("bench_level1", main))
