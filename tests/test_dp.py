"""Generic min-plus Viterbi kernel against exhaustive enumeration of all state sequences."""

import itertools

import jax
import jax.numpy as jnp
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from jaxems import dp, xla

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
