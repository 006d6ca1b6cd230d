"""The NumPy planning pipeline (`jaxems.reference.reference_plan`) against the same stages run
through the JAX kernels (`reference.kernel_plan`: Level 3, Level 2 bisection, Level 1 DP), and
the reference's own building blocks (refined split search, Viterbi loop) against brute force."""

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jaxems import reference as ref
from jaxems import xla
from jaxems.io import load_route
from jaxems.levels import powersplit as ps
from jaxems.params import load_vehicle
from jaxems.route import Row, route_from_rows
from jaxems.switching import SwitchCostParams

VP = load_vehicle()
PRM = SwitchCostParams()
T = 512  # one static step count for both routes: one compilation
_plan = xla.jit(ref.kernel_plan, static_argnames=("dt", "n_steps", "n_iter_l2"))
_split = xla.jit(ps.mode_gear_split)

# standing start, climbs and descents, a stop in the middle, a standing end
STOPS = route_from_rows(
    [Row(*r, line=i + 2) for i, r in enumerate([
        (0, 0, 0, 5), (10, 60, 0, 0), (400, 60, 5, 0), (900, 40, -6, 0), (1300, 0, 0, 20),
        (1310, 60, 3, 0), (2200, 0, 0, 7)])],
    ds=10.0, bucket=512,
)
CASES = {
    "short_track_25t": (load_route("short_track"), VP.replace(mass=25000.0)),
    "stops_20t": (STOPS, VP),
    "stops_38t_1MJ": (STOPS, VP.replace(mass=38000.0, E_b_max=1.0e6)),
}


@pytest.mark.parametrize("name", list(CASES))
def test_plan_agrees_with_kernels(name):
    route, vp = CASES[name]
    assert route.grade.shape == CASES["short_track_25t"][0].grade.shape  # one compilation
    k = _plan(route, vp, PRM, dt=1.0, n_steps=T)
    r = ref.reference_plan(route, vp, dt=1.0, n_steps=T)
    m = r.pred.mask
    # Level 3: the NumPy time grid is the kernel's (speed, power, gradient, mask)
    np.testing.assert_array_equal(np.asarray(k.mask), m)
    np.testing.assert_allclose(np.asarray(k.v), r.pred.v, atol=1e-8)
    np.testing.assert_allclose(np.asarray(k.P_d), r.pred.P_d, rtol=1e-8, atol=1e-3)
    np.testing.assert_allclose(np.asarray(k.grade), r.pred.grade, atol=1e-10)
    # Level 2: the same costate; the reference's final bracket holds the target
    E0 = float(vp.soc0 * vp.E_b_max)
    tol = 1e-3 * float(vp.E_b_max)
    assert abs(float(k.lam) - r.lam) < 1e-6, (float(k.lam), r.lam)
    assert r.costate.E_end_lo >= E0 - tol and r.costate.E_end_hi <= E0 + tol
    # Level 1: the DP's optimum (tie-free), fuel, and the decisions up to ties
    assert r.n_infeasible == 0
    assert float(k.cost) == pytest.approx(r.cost, rel=1e-7)
    agree = ref.compare_plans(r, k)
    assert agree["fuel_rel"] < 5e-3, agree
    assert agree["state_agree"] >= 0.99, agree
    assert r.fuel_J == pytest.approx(np.sum(r.P_f[m]) * 1.0)
    # the reference's path costs what its DP says (stage + switching costs)
    n_g = VP.n_gears
    s = r.state
    tab = ref.split_table(vp, r.pred.P_d, r.pred.v, r.lam)
    H = tab.H.reshape(T, -1)[np.arange(T), s]
    prev = np.concatenate([[ps.MO * n_g if r.pred.v_ref[0] <= 0 else s[0]], s[:-1]])
    brake = ref.ref_braking_loss(vp, tab.H, r.pred.P_d, 1.0)
    sw = [ref.ref_cost_matrix(vp, r.pred.v[j], r.pred.grade[j], r.lam, PRM,
                              brake[j])[prev[j], s[j]]
          for j in np.flatnonzero(m)]
    assert np.sum(H[m]) + np.sum(sw) == pytest.approx(r.cost, rel=1e-12)
    assert np.all(s[~m] == s[np.flatnonzero(m)[-1]])  # masked steps keep the state


@settings(max_examples=20)
@given(P_d=st.floats(-3e5, 4e5), v=st.floats(0.3, 27.0), lam=st.floats(-4.0, -0.5))
def test_refined_split_is_exact(P_d, v, lam):
    """The refined grid search reaches the kernel's exact minimum and never does worse than
    the uniform brute force of 100 001 points."""
    tab = ref.split_table(VP, np.array([P_d]), np.array([v]), lam)
    H = tab.H[0]
    Hu, _, _ = ref.ref_split(VP, P_d, v, lam)
    Hk = np.asarray(_split(VP, P_d, v, lam).H)
    assert np.array_equal(np.isfinite(H), np.isfinite(Hk))
    assert np.array_equal(np.isfinite(H), np.isfinite(Hu))
    f = np.isfinite(H)
    assert np.all(H[f] <= Hu[f] + 1e-9 * np.abs(Hu[f]) + 1e-9)
    np.testing.assert_allclose(H[f], Hk[f], rtol=1e-12, atol=1e-6)


@settings(max_examples=30)
@given(st.integers(0, 2**31 - 1), st.integers(1, 5), st.integers(2, 4))
def test_viterbi_path_is_optimal(seed, n_steps, n_states):
    """Enumerate every path (and the state before step 0) of a small problem."""
    rng = np.random.default_rng(seed)
    stage = rng.integers(0, 6, (n_steps, n_states)).astype(float)
    stage[rng.random(stage.shape) < 0.2] = np.inf
    Cs = rng.integers(0, 4, (n_steps, n_states, n_states)).astype(float)
    Cs[:, np.arange(n_states), np.arange(n_states)] = 0.0
    init = rng.integers(0, 3, n_states).astype(float)
    init[rng.random(n_states) < 0.3] = np.inf
    mask = rng.random(n_steps) < 0.8

    def cost(start, path):
        c, prev = init[start], start
        for k, s in enumerate(path):
            if not mask[k]:
                if s != prev:
                    return np.inf
                continue
            c += Cs[k, prev, s] + stage[k, s]
            prev = s
        return c

    best = min(cost(s0, p) for s0 in range(n_states)
               for p in itertools.product(range(n_states), repeat=n_steps))
    r = ref.viterbi_path(stage, Cs, init, mask)
    assert r.cost == best
    if np.isfinite(best):
        assert cost(r.start, r.path) == best


@settings(max_examples=30, deadline=None)
@given(pts=st.lists(st.tuples(st.integers(-20, 20), st.integers(-50, 50)), min_size=1,
                    max_size=12))
def test_lower_envelope_is_the_lowest_chord_through_each_point(pts):
    """`reference._lower_envelope` (the relaxed DP's step cost, `ref_dp(shared=True)`) against
    brute force: at each x the lowest value of any chord between two points around it (or of
    a point there)."""
    x, y = (np.array(a, float) for a in zip(*pts, strict=True))
    got = ref._lower_envelope(x, y)
    for i, xi in enumerate(x):
        want = y[x == xi].min()
        for j, k in itertools.product(range(len(x)), repeat=2):
            if x[j] < xi < x[k]:
                want = min(want, y[j] + (y[k] - y[j]) * (xi - x[j]) / (x[k] - x[j]))
        assert got[i] == pytest.approx(want, abs=1e-9)
