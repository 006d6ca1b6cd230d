"""Level 1 with switching costs: structured relaxation against the dense matrix, the DP against
a plain NumPy Viterbi loop, MPC against the full horizon, batching and recompilation."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jaxems import dp, stack_vehicles, xla
from jaxems import powertrain as pt
from jaxems import switching as sw
from jaxems.levels import level1 as l1
from jaxems.levels import powersplit as ps
from jaxems.params import load_vehicle
from jaxems.reference import numpy_viterbi, ref_braking_loss, viterbi_path

VP = load_vehicle()
PRM = sw.SwitchCostParams()
T = 24
DT = 1.0


def synthetic_route(T=T, seed=0):
    """Launch, flat, a climb, a steep descent: P_d (W), v (m/s), grade; lambda_b (T,)."""
    rng = np.random.default_rng(seed)
    v = np.full(T, 25 / 3.6) + rng.uniform(-0.3, 0.3, T)
    v[:4] = [0.5, 2.0, 4.0, 6.0]
    grade = np.zeros(T)
    grade[8:13] = 0.06
    grade[15:19] = -0.12
    grade[19:21] = 0.12
    vp25 = VP.replace(mass=25000.0)
    acc = np.gradient(v) / DT
    P_d = np.asarray((pt.road_load(vp25, v, grade) + 25000.0 * acc) * v)
    lam = np.where(np.arange(T) < T // 2, -1.97, -2.1)
    return vp25, P_d, v, grade, lam


# ------------------------------------------------------------------- structured relaxation
@xla.jit
def _relax_all(vp, V, v, grade, lam, prm):
    x = l1.transition_inputs(vp, v, grade, lam, prm)
    k = l1.transition_consts(vp, prm.averaged)
    kd = l1.dense_consts(vp, prm.averaged)
    C = sw.switch_cost_matrix(vp, v, grade, lam, prm)
    return (
        l1.relax_structured(V, x, k),
        l1.relax_same_open_time(V, x, kd),
        dp.relax_dense(V, C),
        C,
    )


@settings(max_examples=25)
@given(
    v=st.floats(0.0, 30.0),
    grade=st.floats(-0.15, 0.15),
    lam=st.floats(-3.0, -1.0),
    averaged=st.sampled_from([0.0, 0.3, 1.0]),
    weight=st.sampled_from([0.0, 1.0, 2.5]),
    dts=st.sampled_from([(1.0, 1.0), (1.5, 0.6), (0.4, 0.9)]),
    seed=st.integers(0, 2**31 - 1),
)
def test_structured_relaxations_equal_dense(v, grade, lam, averaged, weight, dts, seed):
    rng = np.random.default_rng(seed)
    V = rng.normal(0, 2e4, 48)
    V[rng.random(48) < 0.3] = np.inf
    vp = VP.replace(dt_M=dts[0], dt_G=dts[1])
    prm = sw.SwitchCostParams(averaged=averaged, weight=weight)
    (b, a), (bf, af), (bd, _), C = _relax_all(vp, V, v, grade, lam, prm)
    relaxations = [(b, a)] + ([(bf, af)] if dts[0] == dts[1] else [])
    bd, C = np.asarray(bd), np.asarray(C)
    fin = np.isfinite(bd)
    for b, a in relaxations:
        b, a = np.asarray(b), np.asarray(a).astype(int)
        assert np.array_equal(np.isfinite(b), fin)
        np.testing.assert_allclose(b[fin], bd[fin], rtol=1e-12, atol=1e-6)
        np.testing.assert_allclose(
            (V[a] + C[a, np.arange(48)])[fin], bd[fin], rtol=1e-12, atol=1e-6
        )


# ----------------------------------------------------------------------- full horizon DP
_cost_mats = xla.jit(jax.vmap(sw.switch_cost_matrix, in_axes=(None, 0, 0, 0, None, 0)))
_htab = xla.jit(ps.hamiltonian_table)
_tcost = xla.jit(jax.vmap(l1.transition_cost, in_axes=(None, 0, 0, 0, 0, 0, None, 0)))


def _brake(vp, P_d, v, lam):
    """The NumPy loop's braking losses (`ref_braking_loss`) of the route's steps."""
    return ref_braking_loss(vp, _htab(vp, P_d, v, np.broadcast_to(lam, v.shape)).H, P_d, DT)


def _reference_cost(vp, P_d, v, grade, lam, init_state, prm):
    tab = _htab(vp, P_d, v, lam)
    H = np.asarray(tab.H).reshape(len(P_d), -1) * DT
    none = ~np.any(np.isfinite(H), axis=1)
    H[none] = 0.0
    Cs = np.asarray(_cost_mats(vp, v, grade, np.broadcast_to(lam, v.shape), prm,
                               _brake(vp, P_d, v, lam)))
    init = np.full(48, np.inf)
    init[init_state] = 0.0
    return numpy_viterbi(H, Cs, init)


def _check_result(r, vp, P_d, v, grade, lam, prm, init_state, mask=None):
    mask = np.ones(len(v), bool) if mask is None else mask
    state = np.asarray(r.state)
    prev = np.concatenate([[init_state], state[:-1]])
    sc = np.asarray(_tcost(vp, prev, state, v, grade, np.broadcast_to(lam, v.shape), prm,
                           _brake(vp, P_d, v, lam)))
    np.testing.assert_allclose(
        np.asarray(r.switch_cost), np.where(mask, sc, 0.0), rtol=1e-9, atol=1e-6
    )
    H = np.asarray(r.H)
    H = np.where(np.isfinite(H), H, 0.0)
    np.testing.assert_allclose(float(r.cost), np.sum(H * DT) + np.sum(r.switch_cost), rtol=1e-10)
    n_g = VP.n_gears
    assert int(r.n_mode_switches) == int(np.sum(mask & (prev // n_g != state // n_g)))
    assert int(r.n_gear_switches) == int(np.sum(mask & (prev % n_g != state % n_g)))


def test_level1_full_equals_numpy_viterbi():
    vp, P_d, v, grade, lam = synthetic_route()
    init_state = ps.MO * 12 + 0
    r = l1.level1_full(vp, P_d, v, grade, lam, DT, init_mode=ps.MO, init_gear=0, params=PRM)
    ref = _reference_cost(vp, P_d, v, grade, lam, init_state, PRM)
    np.testing.assert_allclose(float(r.cost), ref, rtol=1e-10)
    _check_result(r, vp, P_d, v, grade, lam, PRM, init_state)
    assert int(r.n_infeasible) == 0
    # the path's split (evaluated along the path) is the table's at the chosen states
    tab = _htab(vp, P_d, v, np.broadcast_to(lam, v.shape))
    k, m, g = np.arange(len(v)), np.asarray(r.mode), np.asarray(r.gear)
    for f in ("H", "P_b", "P_e", "P_m", "P_f", "P_brake", "w"):
        np.testing.assert_allclose(np.asarray(getattr(r, f)), np.asarray(getattr(tab, f))[k, m, g],
                                   rtol=1e-12, atol=1e-6, err_msg=f)
    # the paper's narrative: motor-only on the flat, engine on the climb
    assert int(r.mode[6]) == ps.MM and int(r.mode[10]) in (ps.MC, ps.ME)
    # the traction table handed in (as the Level 1 that keeps Level 2's plan does) changes nothing
    trac = l1.traction_table(vp, v, grade, PRM)
    r2 = l1._level1_kernel_jit(vp, P_d, v, grade, lam, DT, np.ones(len(v), bool), ps.MO, 0, PRM,
                               trac=trac)
    for f in ("state", "P_b", "cost"):
        np.testing.assert_array_equal(np.asarray(getattr(r2, f)), np.asarray(getattr(r, f)))


def test_braking_loss_matches_a_loop():
    """`braking_loss` against the NumPy loop on the synthetic route (a descent brakes), with
    unequal open times; zero on driving steps and into the open mode, positive somewhere."""
    vp, P_d, v, grade, lam = synthetic_route(seed=9)
    vp = vp.replace(dt_M=1.5, dt_G=0.5)
    H = _htab(vp, P_d, v, lam).H
    got = np.asarray(jax.vmap(l1.braking_loss, in_axes=(None, 0, 0, None))(vp, H, P_d, DT))
    want = ref_braking_loss(vp, H, P_d, DT)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-9)
    assert np.all(got[P_d >= 0] == 0.0) and np.all(got[:, :, ps.MO * 12:] == 0.0)
    assert np.any(got > 0)


_bloss = xla.jit(l1.braking_loss)
_split = xla.jit(ps.mode_gear_split)


@settings(max_examples=30)
@given(
    P_d=st.floats(-400e3, 400e3),
    v=st.floats(0.5, 30.0),
    lam=st.floats(-4.0, -1.0),
    tau=st.floats(0.1, 3.0),
)
def test_braking_loss_properties(P_d, v, lam, tau):
    """Never negative; zero when driving and into the open mode; it grows with the open time
    up to one step and no further; a braking step's loss is the state's recuperation value."""
    H = _split(VP, P_d, v, lam).H
    vp = VP.replace(dt_M=tau, dt_G=tau)
    b = np.asarray(_bloss(vp, H, P_d, DT))
    assert np.all(b >= 0.0) and np.all(b[:, ps.MO * 12:] == 0.0)
    if P_d >= 0:
        assert np.all(b == 0.0)
        return
    b1 = np.asarray(_bloss(VP.replace(dt_M=1.0, dt_G=1.0), H, P_d, DT))
    np.testing.assert_allclose(b, b1 * min(tau, DT), rtol=1e-12, atol=1e-9)
    Hn = np.asarray(H).reshape(-1)
    h_open = np.min(np.asarray(H)[ps.MO])
    ok = np.isfinite(Hn)
    np.testing.assert_allclose(b1[0][ok], np.maximum(h_open - Hn[ok], 0.0), rtol=1e-12,
                               atol=1e-9)


def test_switching_costs_reduce_switching():
    vp, P_d, v, grade, lam = synthetic_route(seed=1)
    free = l1.level1_full(
        vp, P_d, v, grade, lam, DT, init_mode=ps.MO, init_gear=0, params=PRM._replace(weight=0.0)
    )
    paid = l1.level1_full(vp, P_d, v, grade, lam, DT, init_mode=ps.MO, init_gear=0, params=PRM)
    n = lambda r: int(r.n_mode_switches) + int(r.n_gear_switches)  # noqa: E731
    assert n(paid) <= n(free)
    # without switching costs the DP is the per-step argmin of eq. 36
    tab = _htab(vp, P_d, v, lam)
    Hs, _, _ = ps.optimal_mode_gear(tab)
    np.testing.assert_allclose(np.asarray(free.H), np.asarray(Hs), rtol=1e-12)
    np.testing.assert_allclose(float(free.cost), float(np.sum(Hs) * DT), rtol=1e-12)


@xla.jit
def _full_and_merged(vp, P_d, v, grade, lam):
    tb = l1.dp_inputs(vp, P_d, v, grade, lam, DT, PRM)
    init = l1._init_cost(jnp.int32(ps.MO), jnp.int32(0), 48, 12, tb.stage.dtype)
    mask = jnp.ones(P_d.shape, bool)
    args = (vp.dt_M, vp.dt_G, tb.stage, tb.xs, tb.consts, tb.dconsts, init, mask)
    return l1.solve_dp(*args, fast=False), l1.solve_dp(*args, fast=True), tb


@settings(max_examples=8, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), dlam=st.floats(-0.8, 0.8), conventional=st.booleans())
def test_merged_open_states_give_the_full_dp(seed, dlam, conventional):
    """The fast DP runs the open mode as one state (`merge_open`): the same optimum and path
    as the structured relaxation over all 48 states, because the open states are equivalent."""
    vp, P_d, v, grade, lam = synthetic_route(seed=seed % 1000)
    vp = vp.conventional() if conventional else vp
    full, merged, tb = _full_and_merged(vp, P_d, v, grade, lam + dlam)
    # the equivalence merge_open relies on: open states' costs do not depend on the gear
    o = slice(ps.MO * 12, 48)
    stage, D, trac = np.asarray(tb.stage), np.asarray(tb.dconsts.D), np.asarray(tb.xs.trac)
    assert np.all(stage[:, o] == stage[:, o][:, :1])
    assert np.all(D[o] == D[o][:1]) and np.all(D[:, o] == D[:, o][:, :1])
    assert np.all(trac[:, :, o] == 0.0)
    np.testing.assert_allclose(float(merged.cost), float(full.cost), rtol=1e-12)
    np.testing.assert_array_equal(np.asarray(merged.path), np.asarray(full.path))
    assert int(merged.start) == int(full.start)


def test_unequal_open_times_use_the_structured_relaxation():
    vp, P_d, v, grade, lam = synthetic_route(seed=8)
    vp = vp.replace(dt_M=1.5, dt_G=0.5)
    r = l1.level1_full(vp, P_d, v, grade, lam, DT, init_mode=ps.MO, init_gear=0, params=PRM)
    ref = _reference_cost(vp, P_d, v, grade, lam, ps.MO * 12, PRM)
    np.testing.assert_allclose(float(r.cost), ref, rtol=1e-10)


def test_infeasible_step_passes_through():
    vp, P_d, v, grade, lam = synthetic_route(seed=2)
    P_d = P_d.copy()
    P_d[14] = 5e6  # beyond every mode and gear
    r = l1.level1_full(vp, P_d, v, grade, lam, DT, init_mode=ps.MO, init_gear=0, params=PRM)
    assert int(r.n_infeasible) == 1 and np.isfinite(float(r.cost))
    ref = _reference_cost(vp, P_d, v, grade, lam, ps.MO * 12, PRM)
    np.testing.assert_allclose(float(r.cost), ref, rtol=1e-10)


# ---------------------------------------------------------------------------------- MPC
def test_mpc_with_full_horizon_equals_full_dp():
    vp, P_d, v, grade, lam = synthetic_route(seed=3)
    full = l1.level1_full(vp, P_d, v, grade, lam, DT, init_mode=ps.ME, init_gear=5, params=PRM)
    mpc = l1.level1_mpc(
        vp, P_d, v, grade, lam, DT, init_mode=ps.ME, init_gear=5, params=PRM, horizon=T
    )
    np.testing.assert_allclose(float(mpc.cost), float(full.cost), rtol=1e-12)
    np.testing.assert_array_equal(np.asarray(mpc.state), np.asarray(full.state))


def test_mpc_short_horizon_is_feasible_and_not_better():
    vp, P_d, v, grade, lam = synthetic_route(seed=4)
    mask = np.ones(T, bool)
    mask[-3:] = False  # padded tail
    full = l1.level1_full(vp, P_d, v, grade, lam, DT, mask, ps.MO, 0, PRM)
    mpc = l1.level1_mpc(vp, P_d, v, grade, lam, DT, mask, ps.MO, 0, PRM, horizon=5)
    assert float(mpc.cost) >= float(full.cost) - 1e-6
    _check_result(mpc, vp, P_d, v, grade, lam, PRM, ps.MO * 12, mask)
    assert np.all(np.asarray(mpc.state)[-3:] == np.asarray(mpc.state)[-4])


@pytest.mark.parametrize("horizon", [1, 3, 5])
def test_mpc_short_horizon_follows_a_receding_loop(horizon):
    # the receding horizon as a plain loop: at each step, Viterbi in NumPy over the window
    # from the state the kernel is in; the kernel's decision must start a least-cost path of
    # that window (ties may pick another of equal cost), and masked steps keep the state
    vp, P_d, v, grade, lam = synthetic_route(seed=7)
    mask = np.ones(T, bool)
    mask[9] = False
    mask[-2:] = False
    mpc = l1.level1_mpc(vp, P_d, v, grade, lam, DT, mask, ps.MO, 0, PRM, horizon=horizon)
    H = np.asarray(_htab(vp, P_d, v, lam).H).reshape(T, -1) * DT
    H[~np.any(np.isfinite(H), axis=1)] = 0.0
    Cs = np.asarray(_cost_mats(vp, v, grade, np.broadcast_to(lam, v.shape), PRM,
                               _brake(vp, P_d, v, lam)))
    state = np.asarray(mpc.state)
    prev = ps.MO * VP.n_gears
    for k in range(T):
        if not mask[k]:
            assert state[k] == prev, k
            continue
        win = slice(k, min(k + horizon, T))
        init = np.where(np.arange(H.shape[1]) == prev, 0.0, np.inf)
        best = viterbi_path(H[win], Cs[win], init, mask[win]).cost
        forced = H[win].copy()
        forced[0, np.arange(H.shape[1]) != state[k]] = np.inf
        took = viterbi_path(forced, Cs[win], init, mask[win]).cost
        assert np.isfinite(best) and took <= best + 1e-9 * abs(best) + 1e-6, (k, took, best)
        prev = state[k]
    _check_result(mpc, vp, P_d, v, grade, lam, PRM, ps.MO * VP.n_gears, mask)


# ------------------------------------------------------------------------------ batching
def test_batch_equals_single_and_does_not_recompile():
    routes = [synthetic_route(seed=s) for s in (5, 6)]
    P_d = np.stack([r[1] for r in routes])
    v = np.stack([r[2] for r in routes])
    grade = np.stack([r[3] for r in routes])
    mask = np.ones_like(P_d, bool)
    mask[1, -4:] = False
    vps = stack_vehicles([VP.replace(mass=20000.0), VP.replace(mass=30000.0)])
    lam = np.array([-1.9, -2.2])
    rb = l1.level1_batch(vps, P_d, v, grade, mask, lam, DT, ps.MO, 0, PRM)
    assert rb.cost.shape == (2, 2, 2) and rb.mode.shape == (2, 2, 2, T)
    for i in range(2):
        for j, m in enumerate((20000.0, 30000.0)):
            for k_, la in enumerate(lam):
                # lambda_b as a (T,) array: the compilation test_level1_full_equals_numpy_viterbi
                # made (a scalar compiled level1_full once more)
                r = l1.level1_full(VP.replace(mass=m), P_d[i], v[i], grade[i], np.full(T, la),
                                   DT, mask[i], ps.MO, 0, PRM)
                np.testing.assert_allclose(float(rb.cost[i, j, k_]), float(r.cost), rtol=1e-10)
                np.testing.assert_array_equal(np.asarray(rb.state[i, j, k_]), np.asarray(r.state))
    n0 = l1.TRACES["level1_batch"]
    vps2 = stack_vehicles([VP.replace(mass=22000.0), VP.replace(mass=41000.0, I_e=4.0)])
    rb2 = l1.level1_batch(
        vps2,
        P_d * 1.1,
        v,
        grade,
        mask,
        lam - 0.3,
        0.5,
        ps.ME,
        3,
        PRM._replace(lambda_t=-30e3, averaged=1.0),
    )
    jax.block_until_ready(rb2)
    assert l1.TRACES["level1_batch"] == n0  # new values, same shapes: no new trace
    assert not np.allclose(np.asarray(rb2.cost), np.asarray(rb.cost))
