"""Generic min-plus Viterbi kernel against exhaustive enumeration of all state sequences; dp-bound's
DP over an E_b grid against its loops and, where its grid is exact, brute force."""

import itertools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jaxems import dp, xla
from jaxems import bound as bd
from jaxems import reference as R
from jaxems.levels import powersplit as ps
from jaxems.params import load_vehicle

S, T = 4, 5


def brute_force(stage, C, init, mask):
    """Enumerate every (s_-1, s_0, .., s_{T-1}); C: (T, S, S). Returns (cost, best sequence)."""
    n_t, n_s = stage.shape
    best, arg = np.inf, None
    for seq in itertools.product(range(n_s), repeat=n_t + 1):
        prev, J = seq[0], init[seq[0]]
        ok = True
        for k in range(n_t):
            s = seq[k + 1]
            if not mask[k]:
                if s != prev:  # padded steps keep the state
                    ok = False
                    break
                continue
            J = J + C[k, prev, s] + stage[k, s]
            prev = s
        if ok and J < best:
            best, arg = J, seq
    return best, arg


def random_instance(seed, n_s=S, n_t=T, p_inf=0.2):
    rng = np.random.default_rng(seed)
    stage = rng.uniform(0, 10, (n_t, n_s))
    stage[rng.random((n_t, n_s)) < p_inf] = np.inf
    C = rng.uniform(0, 5, (n_t, n_s, n_s))
    C[:, np.arange(n_s), np.arange(n_s)] = 0.0
    C[rng.random((n_t, n_s, n_s)) < p_inf / 2] = np.inf
    kind = rng.integers(3)
    if kind == 0:
        init = np.full(n_s, np.inf)
        init[rng.integers(n_s)] = 0.0  # a given start state
    elif kind == 1:
        init = np.zeros(n_s)  # free start
    else:
        init = rng.uniform(0, 3, n_s)
    mask = np.ones(n_t, bool)
    if rng.random() < 0.4:
        mask[rng.integers(1, n_t + 1) :] = False  # padding at the end
    return stage, C, init, mask


@xla.jit
def _solve(stage, C, init, mask):
    r = dp.viterbi(stage, dp.dense_transition(C, per_step=True), init, mask)
    s0, c0 = dp.viterbi_first(stage, dp.dense_transition(C, per_step=True), init, mask)
    pc = dp.path_cost(stage, C, init, r.path, r.start, mask)
    return r, s0, c0, pc


@settings(max_examples=60)
@given(seed=st.integers(0, 2**31 - 1))
def test_viterbi_equals_enumeration(seed):
    stage, C, init, mask = random_instance(seed)
    r, s0, c0, pc = _solve(stage, C, init, mask)
    best, seq = brute_force(stage, C, init, mask)
    if not np.isfinite(best):
        assert not bool(r.feasible) and np.isinf(float(r.cost))
        return
    assert bool(r.feasible)
    np.testing.assert_allclose(float(r.cost), best, rtol=1e-12)
    np.testing.assert_allclose(float(c0), best, rtol=1e-12)
    # the returned path achieves the cost; it is the enumerated optimum (continuous costs: unique)
    np.testing.assert_allclose(float(pc), best, rtol=1e-12)
    assert [int(r.start)] + [int(x) for x in r.path] == list(seq)
    assert int(s0) == seq[1]


@xla.jit
def _solve_const(stage, C, init):
    return dp.viterbi(stage, dp.dense_transition(C), init)


def test_constant_transition_and_free_start():
    stage, C, _, _ = random_instance(7, p_inf=0.0)
    init = np.zeros(S)
    r = _solve_const(stage, C[0], init)
    best, _ = brute_force(stage, np.broadcast_to(C[0], (T, S, S)), init, np.ones(T, bool))
    np.testing.assert_allclose(float(r.cost), best, rtol=1e-12)


def test_batch_last_axes_equal_single_solves():
    """Trailing batch axes (the fast layout) give the same result as one solve per member."""
    B = 6
    inst = [random_instance(100 + i) for i in range(B)]
    stage = np.stack([x[0] for x in inst], -1)
    C = np.stack([x[1] for x in inst], -1)
    init = np.stack([x[2] for x in inst], -1)
    mask = np.stack([x[3] for x in inst], -1)
    rb = xla.jit(lambda *a: dp.viterbi(a[0], dp.dense_transition(a[1], per_step=True), a[2], a[3]))(
        stage, C, init, mask
    )
    for i, (st_, C_, in_, m_) in enumerate(inst):
        r, _, _, _ = _solve(st_, C_, in_, m_)
        assert float(rb.cost[i]) == float(r.cost) or (
            np.isinf(float(rb.cost[i])) and np.isinf(float(r.cost))
        )
        if bool(r.feasible):
            np.testing.assert_array_equal(np.asarray(rb.path[:, i]), np.asarray(r.path))


def test_vmap_equals_loop():
    inst = [random_instance(200 + i, p_inf=0.0) for i in range(4)]
    args = [np.stack([x[j] for x in inst]) for j in range(4)]
    rv = jax.vmap(_solve)(*args)[0]
    for i, x in enumerate(inst):
        r = _solve(*x)[0]
        np.testing.assert_allclose(float(rv.cost[i]), float(r.cost), rtol=1e-12)


def test_large_state_count_uses_reduction():
    """S > 64 takes the reduction branch; it agrees with a NumPy Viterbi loop."""
    rng = np.random.default_rng(3)
    n_s, n_t = 70, 6
    stage = rng.uniform(0, 10, (n_t, n_s))
    C = rng.uniform(0, 5, (n_s, n_s))
    init = rng.uniform(0, 1, n_s)
    r = xla.jit(lambda a, b, c: dp.viterbi(a, dp.dense_transition(b), c))(stage, C, init)
    V = init.copy()
    for k in range(n_t):
        V = np.min(V[:, None] + C, axis=0) + stage[k]
    np.testing.assert_allclose(float(r.cost), V.min(), rtol=1e-12)
    assert dp.pointer_dtype(70) == jnp.int8 and dp.pointer_dtype(200) == jnp.int16


def test_float32_pointers_and_inf():
    stage = np.array([[np.inf, 1.0], [np.inf, np.inf]], np.float32)
    C = np.zeros((2, 2), np.float32)
    r = xla.jit(lambda a, b, c: dp.viterbi(a, dp.dense_transition(b), c))(stage, C, np.zeros(2))
    assert not bool(r.feasible)


@pytest.mark.parametrize("n_t", [2000, 2003])  # shifts after blocks of steps / every step
def test_float32_decides_as_float64_over_a_long_route(n_t):
    """A route's accumulated cost (here 2e8) has an ulp of 16 in float32, coarser than the
    differences that decide (multiples of 0.25): the kernel keeps V near zero, so float32 takes
    float64's path (all values are exact in float32 then) and its cost within rounding."""
    rng = np.random.default_rng(7)
    n_s = 6
    stage = 1e5 + 0.25 * rng.integers(0, 40, (n_t, n_s))
    stage[rng.random(stage.shape) < 0.1] = np.inf
    C = 0.25 * rng.integers(0, 80, (n_s, n_s))
    np.fill_diagonal(C, 0.0)
    init = np.zeros(n_s)
    run = xla.jit(lambda a, b, c: dp.viterbi(a, dp.dense_transition(b), c))
    r64 = run(stage, C, init)
    r32 = run(*(x.astype(np.float32) for x in (stage, C, init)))
    assert r32.cost.dtype == np.float32
    np.testing.assert_array_equal(np.asarray(r32.path), np.asarray(r64.path))
    assert int(r32.start) == int(r64.start)
    np.testing.assert_allclose(float(r32.cost), float(r64.cost), rtol=1e-6)
    # the optimum of the plain loop (its ties go elsewhere: the path may differ, not its cost)
    ref = R.viterbi_path(stage, np.broadcast_to(C, (n_t, n_s, n_s)), init)
    assert float(r64.cost) == ref.cost
    assert float(dp.path_cost(stage, C, init, r64.path, r64.start)) == ref.cost
    s0, cost0 = xla.jit(lambda a, b, c: dp.viterbi_first(a, dp.dense_transition(b), c))(
        *(x.astype(np.float32) for x in (stage, C, init)))
    assert int(s0) == int(r64.path[0])
    np.testing.assert_allclose(float(cost0), float(r64.cost), rtol=1e-6)


# ------------------------------------------------------------------------------ dp-bound's DP
class _Pred(NamedTuple):  # what `bound.bound_dp` reads of a Level 3 prediction
    v: Any
    mask: Any
    v_ref: Any


_bound_dp = xla.jit(bd.bound_dp, static_argnums=4)
_BS, _BJ = 8, 3  # states (4 modes x 2 "gears"), candidates per state
_VP = load_vehicle("reference_truck")


def _bound_instance(rng, T, n_E, aligned, standing, mask, reach=1.7):
    """Random tables for `bound_dp` (every state's candidates in `dep`): fuel (T, J, S) with
    some infeasible (BIG) entries, E_b
    changes (multiples of the grid spacing where aligned, else within +-reach cells),
    switching costs (T, S, S)."""
    E_max = float(_VP.E_b_max)
    dE = E_max / (n_E - 1)
    if aligned:
        dEb = rng.integers(-2, 3, (T, _BJ, _BS)) * dE
    else:
        dEb = rng.uniform(-reach, reach, (T, _BJ, _BS)) * dE
    fuel = rng.uniform(0.0, 2e5, (T, _BJ, _BS)) - 1.2 * dEb  # discharging saves fuel
    fuel[rng.random(fuel.shape) < 0.1] = bd.BIG
    C = rng.uniform(0.0, 3e4, (T, _BS, _BS))
    C[:, np.arange(_BS), np.arange(_BS)] = 0.0
    dep = bd.BoundCands(fuel=jnp.asarray(fuel), dEb=jnp.asarray(dEb),
                        P_b=jnp.asarray(rng.uniform(-1e5, 1e5, fuel.shape)))
    tab = bd.BoundTables(dep=dep, fix=bd.BoundCands(*(jnp.zeros((T, 0)),) * 3),
                         C=jnp.asarray(C), lams=jnp.asarray(-np.arange(1.0, _BJ + 1)),
                         lam_end=jnp.asarray(rng.uniform(-3.0, -1.0)), lam_sw=None)
    pred = _Pred(v=jnp.ones(T), mask=jnp.asarray(mask),
                 v_ref=jnp.full(T + 1, 0.0 if standing else 5.0))
    s_init = ps.MO * (_BS // ps.N_MODES) if standing else -1
    return tab, pred, s_init


def _ref_bound(tab, pred, s_init, goal, n_E, penalty):
    full = tab.full()
    return R.ref_bound_dp(full.fuel, full.dEb, tab.C, np.asarray(pred.mask), s_init,
                          float(_VP.soc0 * _VP.E_b_max), float(_VP.E_b_max), goal,
                          float(tab.lam_end), penalty, n_E)


@settings(max_examples=25)
@given(seed=st.integers(0, 2**31 - 1), standing=st.booleans(), pad=st.integers(0, 2),
       goal_frac=st.floats(0.3, 0.7), penalty=st.sampled_from([0.0, 1.0, 10.0]),
       reach=st.sampled_from([1.7, 12.0]))
def test_bound_dp_equals_its_loops(seed, standing, pad, goal_frac, penalty, reach):
    """dp-bound's DP (value function on an E_b grid, interpolated; forward rollout from E0)
    equals the same recursion written as loops, with steps that do not count at the end; also
    where a step moves E_b by more cells than the grid has (reach 12 on 9 points)."""
    T, n_E = 6, 9
    mask = np.arange(T) < T - pad
    tab, pred, s_init = _bound_instance(np.random.default_rng(seed), T, n_E, False, standing,
                                        mask, reach)
    goal = goal_frac * float(_VP.E_b_max)
    bp = _bound_dp(_VP, pred, tab, goal, n_E, penalty)
    ref = _ref_bound(tab, pred, s_init, goal, n_E, penalty)
    np.testing.assert_array_equal(np.asarray(bp.state), ref.state)
    # the costate of each counted step's candidate (steps that do not count have none)
    np.testing.assert_array_equal(np.asarray(bp.lam)[mask], np.asarray(tab.lams)[ref.cand][mask])
    np.testing.assert_allclose(np.asarray(bp.cost), ref.cost, rtol=1e-12, atol=1e-6)
    np.testing.assert_allclose(np.asarray(bp.E), ref.E, rtol=1e-12, atol=1e-6)
    np.testing.assert_allclose(float(bp.E_end), ref.E_end, rtol=1e-12)
    np.testing.assert_allclose(float(bp.lam0), ref.lam0, rtol=1e-9, atol=1e-12)


_bound_pieces = xla.jit(bd.bound_pieces, static_argnums=(6, 7))


@settings(max_examples=40)
@given(seed=st.integers(0, 2**31 - 1), pad=st.integers(0, 3), K=st.sampled_from([2, 3, 64]),
       n_E=st.sampled_from([5, 101]))
def test_bound_pieces_equal_their_loop(seed, pad, K, n_E):
    """dp-bound's plan pieces (`bound_pieces`: the DP's path split where it reaches or leaves a
    limit of the battery, within half a grid cell) equal their loop, on paths that dwell at
    either limit, come near one without reaching it and change within a dwell: the piece of
    each step and each piece's target (the path's change without the drift, the last one's
    moved to the goal), also where the boundaries outnumber the K pieces; the targets sum to
    the goal less the start and the drift of the steps that count."""
    rng = np.random.default_rng(seed)
    T = 40
    E_max = float(_VP.E_b_max)
    tol = 0.5 * E_max / (n_E - 1)
    levels = np.array([0.0, 0.4 * tol, E_max, E_max - 0.9 * tol, 1.5 * tol, 0.5 * E_max])
    E = np.where(rng.random(T) < 0.5, levels[rng.integers(0, 6, T)], rng.uniform(0, E_max, T))
    E = np.repeat(E[::2], 2)[:T]  # dwell two steps at a level
    E[0] = float(_VP.soc0) * E_max
    mask = np.arange(T) < T - pad
    E[~mask] = E[T - pad - 1] if pad else E[-1]
    E_end = float(E[-1]) if pad else float(rng.uniform(0, E_max))
    d = np.where(mask, rng.normal(0.0, 1e4, T), 0.0)
    goal = float(rng.uniform(0.3, 0.7)) * E_max
    pid, target = _bound_pieces(_VP, jnp.asarray(mask), jnp.asarray(E), jnp.asarray(E_end),
                                jnp.asarray(d), jnp.asarray(goal), n_E, K)
    ref_pid, ref_target = R.ref_bound_pieces(mask, E, E_end, d, goal, E_max, n_E, K)
    np.testing.assert_array_equal(np.asarray(pid), ref_pid)
    np.testing.assert_allclose(np.asarray(target), ref_target, rtol=1e-12, atol=1e-6)
    assert float(np.sum(target)) == pytest.approx(goal - E[0] - float(np.sum(d[mask])),
                                                  rel=1e-12, abs=1e-6)
    assert np.all(np.diff(np.asarray(pid)) >= 0) and int(pid[-1]) < K


@settings(max_examples=15)
@given(seed=st.integers(0, 2**31 - 1), standing=st.booleans())
def test_bound_dp_is_the_optimum_where_its_grid_is_exact(seed, standing):
    """Where every E_b change is a multiple of the grid spacing, the interpolation is exact:
    the DP's path (its costs and terminal cost) is the least of every sequence of states and
    candidates within the battery's limits (brute force), as is the loops' value."""
    T, n_E = 4, 5
    tab, pred, s_init = _bound_instance(np.random.default_rng(seed), T, n_E, True, standing,
                                        np.ones(T, bool))
    goal, penalty = 0.5 * float(_VP.E_b_max), 1.0
    bp = _bound_dp(_VP, pred, tab, goal, n_E, penalty)
    d = float(bp.E_end) - goal
    total = float(np.sum(bp.cost)) + float(tab.lam_end) * d + penalty * abs(d)
    full = tab.full()
    best = R.brute_bound(full.fuel, full.dEb, tab.C, s_init, float(_VP.soc0 * _VP.E_b_max),
                         float(_VP.E_b_max), goal, float(tab.lam_end), penalty)
    assert total == pytest.approx(best, rel=1e-12)
    assert _ref_bound(tab, pred, s_init, goal, n_E, penalty).value == pytest.approx(best,
                                                                                  rel=1e-12)


def test_bound_dp_vmapped_equals_each_alone():
    """A batch of dp-bound's DPs (vmapped, as a sweep's chunk runs them; each candidate's
    value-function column read as one slice) equals each DP alone: paths, costs, E_b(tf)."""
    T, n_E = 6, 9
    rng = np.random.default_rng(11)
    insts = [_bound_instance(rng, T, n_E, False, False, np.ones(T, bool)) for _ in range(3)]
    pred = insts[0][1]
    goal, penalty = 0.5 * float(_VP.E_b_max), 1.0
    tabs = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *[tab for tab, _, _ in insts])
    batch = xla.jit(jax.vmap(lambda tab: bd.bound_dp(_VP, pred, tab, goal, n_E, penalty)))(tabs)
    for b, (tab, _, _) in enumerate(insts):
        one = _bound_dp(_VP, pred, tab, goal, n_E, penalty)
        np.testing.assert_array_equal(np.asarray(batch.state[b]), np.asarray(one.state))
        np.testing.assert_allclose(np.asarray(batch.cost[b]), np.asarray(one.cost), rtol=1e-12)
        np.testing.assert_allclose(float(batch.E_end[b]), float(one.E_end), rtol=1e-12)
        np.testing.assert_allclose(float(batch.lam0[b]), float(one.lam0), rtol=1e-9)


@settings(max_examples=10)
@given(seed=st.integers(0, 2**31 - 1), standing=st.booleans(), n_dep=st.integers(0, _BS),
       pad=st.integers(0, 2))
def test_bound_dp_reads_one_candidate_where_they_are_equal(seed, standing, n_dep, pad):
    """Where the states from n_dep on have the same candidate at every costate (dp-bound's
    modes without a battery-power choice), tables that hold their one candidate apart
    (`BoundTables.fix`, read once by the backward step) give the same DP as the tables with it
    repeated over the costates: path, costate, costs, battery power, E_b(tf) and the costate
    at t0, to the bit; `full` gives those repeated tables back."""
    T, n_E = 6, 9
    tab, pred, _ = _bound_instance(np.random.default_rng(seed), T, n_E, False, standing,
                                   np.arange(T) < T - pad)
    same = lambda a: a.at[:, :, n_dep:].set(a[:, :1, n_dep:])  # noqa: E731
    tab = tab._replace(dep=bd.BoundCands(*map(same, tab.dep)))
    split = tab._replace(dep=bd.BoundCands(*(a[:, :, :n_dep] for a in tab.dep)),
                         fix=bd.BoundCands(*(a[:, 0, n_dep:] for a in tab.dep)))
    for a, b in zip(split.full(), tab.dep, strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    goal, penalty = 0.5 * float(_VP.E_b_max), 1.0
    full = _bound_dp(_VP, pred, tab, goal, n_E, penalty)
    one = _bound_dp(_VP, pred, split, goal, n_E, penalty)
    for a, b in zip(full, one, strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
