"""Level 3 eco-driving (velocity optimisation): NumPy DP reference, constraints, soft minimum,
gradients, vmap == loop, trip-time matching, no retracing.

Every route here has 64 nodes after padding (ds is a leaf), so the optimiser compiles once.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jaxems import xla
from jaxems.levels import velocity as vel
from jaxems.levels.powersplit import mode_gear_split
from jaxems.levels.velocity import (
    ECO_TARGET_FAST,
    ECO_TARGET_MISSED,
    ECO_TARGET_SLOW,
    V_CRAWL,
    eco_cost,
    eco_cost_exact,
    match_trip_time,
    optimize_velocity,
    optimize_velocity_batch,
    profile_from_speed,
    project_speeds,
    restore_feasible,
    soft_min_hamiltonian,
    speed_bounds,
    velocity_profile,
)
from jaxems.params import load_vehicle
from jaxems.reference import (
    _veh,
    a_fwd,
    ref_eco_cell,
    ref_eco_dp,
    ref_hamiltonian_min,
    ref_pieces,
    ref_time_grid,
)
from jaxems.route import Route, Row, n_nodes, route_from_rows

VP = load_vehicle()
LAM_B = -2.2


def make(*data, ds=50.0):
    rows = [Row(*r, line=i + 2) for i, r in enumerate(data)]
    return route_from_rows(rows, ds=ds, bucket=64)


# flying start and free end at 80 km/h; a 4 % hill up then down
HILL = make((0, 80, 0, 0), (300, 80, 4, 0), (1000, 80, -4, 0), (1700, 80, 0, 0), (2400, 80, 0, 0))
FLAT = make((0, 80, 0, 0), (6000, 80, 0, 0), ds=100.0)
# standing start, a stop half way, standing end; climbs and descents
STOPS = make((0, 0, 0, 5), (10, 70, 2, 0), (900, 70, -3, 0), (1500, 0, 0, 10), (1510, 70, 0, 0),
             (2200, 0, 0, 3))
for _r in (HILL, FLAT, STOPS):
    assert _r.grade.shape == (64,)

TRACES = [0]


def _opt(route, vp, lambda_t, lam_b, switch_weight=vel.SWITCH_WEIGHT):
    TRACES[0] += 1
    return optimize_velocity(route, vp, lambda_t, lam_b, switch_weight=switch_weight)


def _f64(x):
    """A scalar as a float64 array: a Python float is weakly typed and a NumPy one is not, and
    jit compiles once for each; the wrappers below pass every scalar this way (and every
    argument, defaults included), so that each kernel compiles once for this module."""
    return np.asarray(x, dtype=float)


_OPT = xla.jit(_opt)


def OPT(route, vp, lambda_t, lam_b, switch_weight=vel.SWITCH_WEIGHT):
    return _OPT(route, vp, _f64(lambda_t), _f64(lam_b), _f64(switch_weight))


EXACT = xla.jit(eco_cost_exact)


@xla.jit
def _cost_and_grads(route, v, lambda_t, tau):
    """(soft cost, its gradient, the exact cost's gradient, the switching proxy's gradient)."""
    return (eco_cost(route, VP, v, lambda_t, LAM_B, tau),
            jax.grad(eco_cost, argnums=2)(route, VP, v, lambda_t, LAM_B, tau),
            jax.grad(eco_cost_exact, argnums=2)(route, VP, v, lambda_t, LAM_B),
            jax.grad(vel.eco_regulariser, argnums=1)(route, v, 1e5))


_MATCH = xla.jit(match_trip_time)


def MATCH(route, vp, target_trip_time, lam_b, overspeed=0.0):
    return _MATCH(route, vp, _f64(target_trip_time), _f64(lam_b), overspeed=_f64(overspeed))


PROJECT = xla.jit(project_speeds)
PROFILE = xla.jit(velocity_profile)
BOUNDS = xla.jit(lambda route: speed_bounds(route, VP))
MGS = xla.jit(lambda P_d, v, lam: mode_gear_split(VP, P_d, v, lam).H)


@xla.jit
def _h_min(P_d, v):
    H = jax.vmap(mode_gear_split, in_axes=(None, 0, 0, None))(VP, P_d, v, LAM_B).H
    return soft_min_hamiltonian(H, P_d, VP, None)


def kernel_h_min(P_d, v, chunk=8192):
    """The kernel's exact minimum over modes and gears, in fixed chunks (one compilation)."""
    P_d, v = np.ravel(P_d), np.ravel(v)
    n = P_d.size
    m = -(-n // chunk) * chunk
    P = np.zeros(m)
    s = np.full(m, 10.0)
    P[:n], s[:n] = P_d, v
    out = [np.asarray(_h_min(P[a:a + chunk], s[a:a + chunk])) for a in range(0, m, chunk)]
    return np.concatenate(out)[:n]


def _valid(route, x):
    return np.asarray(x)[: n_nodes(route)]


def _check_constraints(route, vp, res, tol=1e-9):
    n = n_nodes(route)
    v = _valid(route, res.profile.v)
    hi = _valid(route, res.v_upper)
    stop = _valid(route, route.stop)
    assert np.all(v <= hi + tol)
    assert np.all(v[stop > 0] == 0.0)
    assert np.all(v[stop == 0] >= np.minimum(V_CRAWL, hi[stop == 0]) - tol)
    assert v[0] == pytest.approx(hi[0], abs=1e-9)  # the ends are Level 3's
    assert v[-1] == pytest.approx(hi[-1], abs=1e-6)
    # acceleration limits (NumPy forward traction limit at the cell's start speed)
    f = _veh(vp)
    ds = float(route.ds)
    g = _valid(route, route.grade)
    a = (v[1:] ** 2 - v[:-1] ** 2) / (2 * ds)
    a_hi = np.array([a_fwd(f, v[i], g[i], f.w_pred) for i in range(n - 1)])
    assert np.all(a <= a_hi + 1e-6)
    assert np.all(a >= -f.a_min - 1e-6)
    assert float(res.acc_violation) < 1e-3  # what the restoration had left to remove


# ------------------------------------------------------------------------- NumPy references
def test_ref_eco_dp_equals_brute_force():
    """The DP's optimum equals an enumeration of every path on a tiny route."""
    tiny = route_from_rows([Row(0, 60, 0, 0, 2), Row(100, 60, 5, 0, 3), Row(400, 60, -2, 0, 4)],
                           ds=100.0, bucket=None)
    grid = np.array([10.0, 12.0, 14.0, 15.5, 16.0])
    lt = 8e4
    dp = ref_eco_dp(tiny, VP, lt, LAM_B, grid)  # NumPy brute-force Hamiltonian (split_table)
    n = n_nodes(tiny)
    env = dp.envelope
    f = _veh(VP)
    g = np.asarray(tiny.grade)
    cand = [[env[0]]] + [sorted(set(grid[grid < env[i]]) | {env[i]}) for i in range(1, n - 1)]
    cand += [[env[-1]]]
    best = math.inf
    for path in np.array(np.meshgrid(*cand, indexing="ij")).reshape(n, -1).T:
        a = (path[1:] ** 2 - path[:-1] ** 2) / 200.0
        a_hi = np.array([a_fwd(f, path[i], g[i], f.w_pred) for i in range(n - 1)])
        if np.any(a > a_hi + 1e-9) or np.any(a < -f.a_min - 1e-9):
            continue
        P, vm, dt = ref_eco_cell(VP, path[:-1], path[1:], g[:-1], 100.0)
        best = min(best, float(np.sum((ref_hamiltonian_min(VP, P, vm, LAM_B) + lt) * dt)))
    assert dp.cost == pytest.approx(best, rel=1e-12)
    assert dp.trip_time == pytest.approx(ref_pieces(tiny, dp.v)[1])


def test_optimum_matches_numpy_dp_on_a_hill():
    """Without the switching proxy, within 1 % of a DP over a 0.1 m/s speed grid from 8 m/s
    (the optimum stays above 12 m/s; and not below the DP by more than the grid's resolution
    can explain); the kernel's cell model gives the DP path the DP's cost. With it, the price
    of a smoother profile is small."""
    lt = 1e5
    dp = ref_eco_dp(HILL, VP, lt, LAM_B, np.arange(8.0, 22.3, 0.1), h_min=kernel_h_min)
    v_dp = np.zeros(64)
    v_dp[: n_nodes(HILL)] = dp.v
    assert float(EXACT(HILL, VP, jnp.asarray(v_dp), lt, LAM_B)) == pytest.approx(dp.cost, rel=1e-9)
    # the kernel's minimum over modes and gears = NumPy's brute force along the DP path
    P, vm, dt = ref_eco_cell(VP, dp.v[:-1], dp.v[1:], _valid(HILL, HILL.grade)[:-1],
                             float(HILL.ds))
    np.testing.assert_allclose(ref_hamiltonian_min(VP, P, vm, LAM_B), kernel_h_min(P, vm),
                               rtol=1e-7, atol=1e-2)
    res = OPT(HILL, VP, lt, LAM_B, 0.0)
    assert int(res.status) == 0
    cost = float(res.cost_exact)
    assert cost <= dp.cost * 1.01
    assert cost >= dp.cost * (1 - 0.005)
    assert cost < float(EXACT(HILL, VP, res.v_level3, lt, LAM_B)) * 0.95  # it pays to optimise
    _check_constraints(HILL, VP, res)
    smooth = OPT(HILL, VP, lt, LAM_B)  # the default switching proxy
    assert float(smooth.cost_exact) <= dp.cost * 1.02
    _check_constraints(HILL, VP, smooth)


def test_flat_route_cruises_at_the_best_constant_speed():
    """Away from the ends (entered and left at 80 km/h) a flat route is driven at one speed:
    the minimiser of (H(F_0(v) v, v) + lambda_t) / v found by a NumPy search; faster as
    lambda_t grows, at the limit when time is dear."""
    n = n_nodes(FLAT)
    mid = slice(n // 3, 2 * n // 3)
    c = np.linspace(5.0, 22.22, 1723)
    P, vm, _ = ref_eco_cell(VP, c, c, 0.0, float(FLAT.ds))
    h = kernel_h_min(P, vm)
    speeds = []
    for lt in (5e4, 1e5, 1.5e5):
        res = OPT(FLAT, VP, lt, LAM_B)
        v = _valid(FLAT, res.profile.v)[mid]
        assert np.ptp(v) < 0.2
        best = c[np.argmin((h + lt) / c)]
        assert v.mean() == pytest.approx(best, abs=0.05)
        speeds.append(v.mean())
        _check_constraints(FLAT, VP, res)
    assert speeds[0] < speeds[1] < speeds[2]
    fast = OPT(FLAT, VP, 1e6, LAM_B)
    np.testing.assert_allclose(_valid(FLAT, fast.profile.v), 80 / 3.6, rtol=1e-12)


# ------------------------------------------------------------------------------ constraints
@pytest.mark.parametrize("mass", [20000.0, 40000.0])
def test_constraints_with_stops(mass):
    vp = VP.replace(mass=mass)
    res = OPT(STOPS, vp, 1e5, LAM_B)
    assert int(res.status) == 0
    _check_constraints(STOPS, vp, res)
    assert float(res.trip_time) >= float(PROFILE(STOPS, vp).trip_time)
    assert float(res.cost_exact) <= float(EXACT(STOPS, vp, res.v_level3, 1e5, LAM_B))


@settings(max_examples=25)
@given(st.lists(st.floats(0.0, 30.0), min_size=64, max_size=64), st.sampled_from([0, 1]))
def test_projection_is_feasible(raw, which):
    """project_speeds: within the bounds and the acceleration limits (traction at v_ref),
    whatever it is given; a feasible profile is left as it is."""
    route = (HILL, STOPS)[which]
    lo, hi, l3 = BOUNDS(route)
    v = np.asarray(PROJECT(route, VP, jnp.asarray(raw), hi, lo, hi))
    n = n_nodes(route)
    vv, lo_, hi_ = v[:n], np.asarray(lo)[:n], np.asarray(hi)[:n]
    assert np.all(vv >= lo_ - 1e-9) and np.all(vv <= hi_ + 1e-9)
    f = _veh(VP)
    g = np.asarray(route.grade)[:n]
    a = (vv[1:] ** 2 - vv[:-1] ** 2) / (2 * float(route.ds))
    a_hi = np.array([a_fwd(f, hi_[i], g[i], f.w_pred) for i in range(n - 1)])
    assert np.all(a <= a_hi + 1e-9) and np.all(a >= -f.a_min - 1e-9)  # traction at v_ref = hi
    again = np.asarray(PROJECT(route, VP, jnp.asarray(v), hi, lo, hi))
    np.testing.assert_allclose(again, v, atol=1e-12)
    np.testing.assert_allclose(np.asarray(PROJECT(route, VP, l3.v, l3.v, lo, hi)),
                               np.asarray(l3.v), atol=1e-12)


def loop_project(route, v, v_ref, lo, hi):
    """`project_speeds` as plain loops (its docstring's four recursions in v^2)."""
    f, n, ds = _veh(VP), n_nodes(route), float(route.ds)
    g = np.asarray(route.grade)[:n]
    c = np.array([2 * ds * a_fwd(f, v_ref[i], g[i], f.w_pred) for i in range(n - 1)])
    b = 2 * ds * f.a_min
    L = lo[:n] ** 2
    for i in range(n - 2, -1, -1):  # the end can be reached
        L[i] = max(L[i], L[i + 1] - c[i])
    for i in range(n - 1):  # the start can brake to them
        L[i + 1] = max(L[i + 1], L[i] - b)
    x = np.clip(np.clip(v[:n], lo[:n], hi[:n]) ** 2, L, hi[:n] ** 2)
    for i in range(n - 1):
        x[i + 1] = min(x[i + 1], x[i] + c[i])
    for i in range(n - 2, -1, -1):
        x[i] = min(x[i], x[i + 1] + b)
    return np.sqrt(np.maximum(np.maximum(x, np.minimum(L, hi[:n] ** 2)), 0.0))


def loop_restore(route, v):
    """`restore_feasible` as plain loops: forward at the traction at each node's speed, never
    below the crawl floor (0 at stops), then backward at a_min."""
    f, n, ds = _veh(VP), n_nodes(route), float(route.ds)
    g, stop = np.asarray(route.grade)[:n], np.asarray(route.stop)[:n]
    lim = np.where(stop > 0, 0.0, np.minimum(np.asarray(route.vmax)[:n], f.v_cruise))
    floor = np.where(stop > 0, 0.0, np.minimum(V_CRAWL, lim))
    out = np.array(v[:n], dtype=float)
    for i in range(n - 1):
        a = a_fwd(f, out[i], g[i], f.w_pred)
        nxt = min(out[i + 1], math.sqrt(max(out[i] ** 2 + 2 * a * ds, 0.0)))
        out[i + 1] = max(nxt, min(floor[i + 1], out[i + 1]))
    for i in range(n - 2, -1, -1):
        out[i] = min(out[i], math.sqrt(out[i + 1] ** 2 + 2 * f.a_min * ds))
    return out


RESTORE = xla.jit(restore_feasible)


@settings(max_examples=20)
@given(st.lists(st.floats(0.0, 30.0), min_size=64, max_size=64),
       st.lists(st.floats(0.5, 30.0), min_size=64, max_size=64), st.sampled_from([0, 1]))
def test_projection_and_restoration_are_their_loops(raw, ref, which):
    """project_speeds (four associative min-plus scans) and restore_feasible (two sequential
    scans) against their recursions written as loops, on random speeds and traction speeds
    v_ref, a route with a hill and one with stops (an audit found only their properties
    tested)."""
    route = (HILL, STOPS)[which]
    n = n_nodes(route)
    lo, hi, _ = BOUNDS(route)
    lo, hi = np.asarray(lo), np.asarray(hi)
    raw, ref = np.asarray(raw), np.minimum(np.asarray(ref), hi)
    got = np.asarray(PROJECT(route, VP, jnp.asarray(raw), jnp.asarray(ref), lo, hi))
    np.testing.assert_allclose(got[:n], loop_project(route, raw, ref, lo, hi), rtol=1e-10,
                               atol=1e-10)
    assert np.all(got[n:] == 0.0)
    below = np.minimum(raw, hi)  # restore_feasible only lowers: from speeds within the limits
    got = np.asarray(RESTORE(route, VP, jnp.asarray(below)))
    np.testing.assert_allclose(got[:n], loop_restore(route, below), rtol=1e-10, atol=1e-10)
    assert np.all(got[:n] <= np.maximum(below[:n], V_CRAWL) + 1e-12) and np.all(got[n:] == 0)


def test_min_plus_scan_matches_loop():
    rng = np.random.default_rng(0)
    A, B = rng.normal(size=40), rng.normal(size=40)
    fwd, bwd = A.copy(), A.copy()
    for i in range(1, 40):
        fwd[i] = min(A[i], fwd[i - 1] + B[i])
    for i in range(38, -1, -1):
        bwd[i] = min(A[i], bwd[i + 1] + B[i])
    np.testing.assert_allclose(vel._min_plus_scan(jnp.asarray(A), jnp.asarray(B)), fwd)
    np.testing.assert_allclose(vel._min_plus_scan(jnp.asarray(A), jnp.asarray(B), True), bwd)


# --------------------------------------------------------------- soft minimum and gradients
SOFT = xla.jit(soft_min_hamiltonian)
SOFT_GRAD = xla.jit(jax.grad(lambda H, P, tau: soft_min_hamiltonian(H, P, VP, tau), (0, 1)))


@settings(max_examples=30)
@given(st.floats(-4e5, 6e5), st.floats(0.3, 25.0), st.floats(-4.0, -1.0),
       st.sampled_from([10.0, 100.0, 1000.0]))
def test_soft_min_is_numpys_log_sum_exp(P_d, v, lam, tau):
    """The soft minimum over the feasible modes and gears against NumPy's -tau log sum
    exp(-H / tau) (scipy's shift by the minimum), and the exact minimum; the penalty where
    nothing can deliver (an audit found only its bounds tested)."""
    H = np.asarray(MGS(P_d, v, lam))
    ok = np.isfinite(H)
    got = float(SOFT(jnp.asarray(H), P_d, VP, tau))
    hard = float(SOFT(jnp.asarray(H), P_d, VP, None))
    if ok.any():
        h = H[ok]
        want = h.min() - tau * np.log(np.sum(np.exp(-(h - h.min()) / tau)))
        assert got == pytest.approx(want, rel=1e-12, abs=1e-9) and hard == h.min()
    else:
        pen = vel.P_PENALTY_W + 2.0 * max(P_d, 0.0) / float(VP.eta_e)
        assert got == hard == pytest.approx(pen, rel=1e-12)
    none = np.full_like(H, np.inf)  # nothing feasible: the penalty, increasing in P_d
    assert float(SOFT(jnp.asarray(none), P_d, VP, tau)) == pytest.approx(
        vel.P_PENALTY_W + 2.0 * max(P_d, 0.0) / float(VP.eta_e), rel=1e-12)


@settings(max_examples=30)
@given(st.floats(-4e5, 6e5), st.floats(0.3, 25.0), st.floats(-4.0, -1.0),
       st.sampled_from([10.0, 100.0, 1000.0]))
def test_soft_min_bounds_and_finite_gradient(P_d, v, lam, tau):
    H = MGS(P_d, v, lam)
    hard = float(SOFT(H, P_d, VP, None))
    soft = float(SOFT(H, P_d, VP, tau))
    assert math.isfinite(soft) and math.isfinite(hard)
    n_ok = int(np.isfinite(np.asarray(H)).sum())
    if n_ok:
        assert hard == float(np.min(np.asarray(H)))
        assert hard - tau * math.log(n_ok) - 1e-6 <= soft <= hard + 1e-6
    else:  # nothing can deliver P_d: the finite penalty
        assert hard == soft == pytest.approx(vel.P_PENALTY_W + 2 * max(P_d, 0) / 0.45)
    gH, gP = SOFT_GRAD(H, jnp.asarray(P_d), tau)
    assert np.all(np.isfinite(np.asarray(gH))) and math.isfinite(float(gP))
    assert np.all(np.asarray(gH)[~np.isfinite(np.asarray(H))] == 0.0)


def test_eco_cost_gradient_finite_with_stops_and_infeasible_states():
    lo, hi, l3 = BOUNDS(STOPS)
    rng = np.random.default_rng(3)
    profiles = [l3.v, jnp.asarray(np.asarray(l3.v) * 0.7)]
    for _ in range(3):
        raw = rng.uniform(0.0, 25.0, 64)
        profiles.append(PROJECT(STOPS, VP, jnp.asarray(raw), hi, lo, hi))
    wild = np.asarray(l3.v).copy()
    wild[1] = 20.0  # 0 -> 20 m/s within one cell: beyond every (mode, gear)
    profiles.append(jnp.asarray(wild))
    P_d, v_mean, _, _ = vel._cell_model(STOPS, VP, jnp.asarray(wild))
    H = np.stack([np.asarray(MGS(p, s, LAM_B)) for p, s in zip(P_d[:n_nodes(STOPS) - 1],
                                                              v_mean, strict=False)])
    finite = np.isfinite(H)
    assert (~finite).any(axis=(1, 2)).all()  # every cell has infeasible (mode, gear) entries
    assert not finite[0].any()  # the wild cell: none is feasible
    for v in profiles:
        cost, *grads = _cost_and_grads(STOPS, v, 1e5, 100.0)
        assert math.isfinite(float(cost))
        assert all(np.all(np.isfinite(np.asarray(g))) for g in grads)


def test_gradient_matches_finite_differences():
    v0 = jnp.asarray(np.asarray(PROFILE(HILL, VP).v) * 0.9)
    g = _cost_and_grads(HILL, v0, 1e5, 100.0)[1]
    rng = np.random.default_rng(5)
    for _ in range(3):
        d = jnp.asarray(rng.normal(size=64) * np.asarray(HILL.mask))
        h = 1e-5
        fd = (_cost_and_grads(HILL, v0 + h * d, 1e5, 100.0)[0]
              - _cost_and_grads(HILL, v0 - h * d, 1e5, 100.0)[0]) / (2 * h)
        assert float(g @ d) == pytest.approx(float(fd), rel=1e-5)


def _maxima(v):
    d = np.diff(v)
    s = np.sign(d[np.abs(d) > 1e-6])
    return int(np.sum((s[1:] < 0) & (s[:-1] > 0)))


def test_switching_proxy_smooths_the_profile():
    """eco_regulariser is switch_weight x the (smoothed) total variation of the acceleration;
    with it the profile over a hill has fewer speed peaks and less of that variation."""
    v = _valid(HILL, PROFILE(HILL, VP).v) * np.linspace(1.0, 0.8, n_nodes(HILL))
    a = np.diff(v**2) / (2 * float(HILL.ds))
    da = np.diff(a)
    eps = vel.ACC_EPS
    expect = 3e4 * np.sum(np.sqrt(da**2 + eps**2) - eps)
    padded = np.zeros(64)
    padded[: v.size] = v
    assert float(vel.eco_regulariser(HILL, jnp.asarray(padded), 3e4)) == pytest.approx(expect)
    bare = OPT(HILL, VP, 2e5, LAM_B, 0.0)
    smooth = OPT(HILL, VP, 2e5, LAM_B, 1e5)
    vb, vs = _valid(HILL, bare.profile.v), _valid(HILL, smooth.profile.v)
    assert _maxima(vs) < _maxima(vb)
    tv = [float(vel.eco_regulariser(HILL, x.profile.v, 1.0)) for x in (bare, smooth)]
    assert tv[1] < tv[0]
    assert float(smooth.regulariser) == pytest.approx(1e5 * tv[1], rel=1e-9)
    # slower ahead of the crest (node 20) than on the approach, faster again on the descent
    crest = int(round(1000 / float(HILL.ds)))
    assert vs[crest] < vs[crest - 6] and vs[crest] < vs[crest + 6]


def test_table_is_close_to_the_kernel():
    """The tabulated soft minimum the optimiser steps on, against the kernel per point, and,
    exactly, its nodes and its bilinear lookup against NumPy's (an audit found the table
    compared only within a median 50 W)."""
    tab = vel.eco_table(VP, LAM_B, 22.4, 100.0)
    rng = np.random.default_rng(1)
    v = rng.uniform(3.0, 22.3, 2000)
    P = rng.uniform(-3e5, 3e5, 2000)
    Ht = np.asarray(vel.table_hamiltonian(tab, VP, jnp.asarray(P), jnp.asarray(v)))
    He = np.array([float(SOFT(MGS(p, s, LAM_B), p, VP, 100.0))
                   for p, s in zip(P[:200], v[:200], strict=True)])
    err = np.abs(Ht[:200] - He)
    ok = He < vel.P_PENALTY_W
    assert np.median(err[ok]) < 50.0 and np.percentile(err[ok], 95) < 3e3
    # exactly: the table's nodes are the kernel's soft minimum there, and between them the
    # lookup is NumPy's bilinear interpolation of the nodes (clipped to the table's edges; the
    # penalty above its power range)
    H = np.asarray(tab.H)
    v0, dv, P0, dP = (float(x) for x in (tab.v0, tab.dv, tab.P0, tab.dP))
    for i, j in ((0, 0), (37, 101), (159, 383), (80, 200)):
        vi, Pj = v0 + dv * i, P0 + dP * j
        assert H[i, j] == pytest.approx(float(SOFT(MGS(Pj, vi, LAM_B), Pj, VP, 100.0)),
                                        rel=1e-12, abs=1e-6)
    P = np.concatenate([P, [float(tab.P_hi) * 1.01, P0 - 1e4]])
    v = np.concatenate([v, [10.0, 30.0]])
    Ht = np.asarray(vel.table_hamiltonian(tab, VP, jnp.asarray(P), jnp.asarray(v)))
    x = np.clip((v - v0) / dv, 0, H.shape[0] - 1)
    y = np.clip((P - P0) / dP, 0, H.shape[1] - 1)
    i, j = np.minimum(x.astype(int), H.shape[0] - 2), np.minimum(y.astype(int), H.shape[1] - 2)
    fx, fy = x - i, y - j
    want = ((1 - fx) * (1 - fy) * H[i, j] + (1 - fx) * fy * H[i, j + 1]
            + fx * (1 - fy) * H[i + 1, j] + fx * fy * H[i + 1, j + 1])
    above = P > float(tab.P_hi)
    want[above] = vel.P_PENALTY_W + 2.0 * P[above] / float(VP.eta_e)
    np.testing.assert_allclose(Ht, want, rtol=1e-12, atol=1e-6)
    assert above.sum() == 1


# ------------------------------------------------------------ profile -> time grid pipeline
def test_optimised_profile_runs_through_resample():
    """profile_from_speed + resample on an optimised profile = the NumPy time grid of its node
    speeds (distance, mean power, speed at t_k), as for Level 3's own profile."""
    res = OPT(STOPS, VP, 1e5, LAM_B)
    n = n_nodes(STOPS)
    v = _valid(STOPS, res.profile.v)
    assert float(res.trip_time) == pytest.approx(ref_pieces(STOPS, v)[1], rel=1e-12)
    again = profile_from_speed(STOPS, VP, res.profile.v)
    np.testing.assert_allclose(np.asarray(again.t_dep), np.asarray(res.profile.t_dep))
    T = 512
    pred = vel._resample_jit(STOPS, VP, res.profile, 1.0, n_steps=T)
    dist, P, v_at, trip = ref_time_grid(STOPS, VP, v, 1.0, T)
    assert trip == pytest.approx(float(pred.trip_time), rel=1e-12)
    np.testing.assert_allclose(np.asarray(pred.v), dist, atol=1e-8)
    np.testing.assert_allclose(np.asarray(pred.P_d), P, rtol=1e-8, atol=1e-3)
    m = np.asarray(pred.mask)
    np.testing.assert_allclose(np.asarray(pred.v_ref)[m], v_at[m], atol=1e-9)
    assert np.sum(np.asarray(pred.v)) == pytest.approx(float(STOPS.length), rel=1e-9)
    assert n == int(np.sum(np.asarray(STOPS.mask)))


# ---------------------------------------------------------------- batching, jit, matching
def test_vmap_over_vehicles_equals_loop():
    vps = [VP.replace(mass=m) for m in (15000.0, 20000.0, 30000.0)]
    lts = np.array([8e4, 1e5, 1.5e5])
    batch = optimize_velocity_batch(HILL, vps, lts, LAM_B)
    for b, vp in enumerate(vps):
        one = OPT(HILL, vp, lts[b], LAM_B)
        # the same computation, compiled batched: rounding differences, amplified by the
        # non-smooth iteration, move single nodes by centimetres per second at most
        np.testing.assert_allclose(np.asarray(batch.profile.v)[b], np.asarray(one.profile.v),
                                   atol=0.1)
        for name in ("cost_exact", "energy_J", "trip_time"):
            assert float(getattr(batch, name)[b]) == pytest.approx(float(getattr(one, name)),
                                                                   rel=1e-3)
    n = vel.TRACES["optimize_velocity_batch"]
    routes = Route(*(np.stack(leaves) for leaves in zip(HILL, STOPS, FLAT, strict=True)))
    optimize_velocity_batch(routes, VP.replace(mass=25000.0), 2e5, -2.0)
    assert vel.TRACES["optimize_velocity_batch"] == n  # new routes, values: no new trace


def test_new_values_do_not_retrace():
    OPT(HILL, VP, 1e5, LAM_B)
    n = TRACES[0]
    for route, mass, lt, lb in ((HILL, 31000.0, 3e5, -2.0), (STOPS, 12000.0, 5e4, -2.5),
                                (FLAT, 20000.0, 7e4, LAM_B)):
        OPT(route, VP.replace(mass=mass, v_cruise=70 / 3.6), lt, lb)
    assert TRACES[0] == n


def test_match_trip_time():
    l3_trip = float(PROFILE(HILL, VP).trip_time)
    target = 1.12 * l3_trip
    lt, res = MATCH(HILL, VP, target, LAM_B)
    assert int(res.status) == 0
    assert abs(float(res.trip_time) / target - 1) < 5e-3
    assert float(res.lambda_t) == float(lt)
    one = OPT(HILL, VP, lt, LAM_B)  # what optimize_velocity gives at that price
    assert float(one.trip_time) == pytest.approx(target, rel=5e-3)
    # faster than Level 3 (the envelope) cannot be had: flagged, the fastest is returned
    lt_f, fast = MATCH(HILL, VP, 0.95 * l3_trip, LAM_B)
    assert int(fast.status) == ECO_TARGET_FAST
    assert float(fast.trip_time) >= l3_trip - 1e-9
    # slower than the cheapest second's optimum: flagged as such
    _, slow = MATCH(HILL, VP, 20.0 * l3_trip, LAM_B)
    assert int(slow.status) == ECO_TARGET_SLOW


@pytest.mark.parametrize("rel, all_fast, all_slow, want", [
    (0.02, False, True, ECO_TARGET_FAST),  # too slow at every price: beyond the envelope
    (-0.02, True, False, ECO_TARGET_SLOW),
    # the trip time jumps across the target between two prices: missed, not "too fast"
    (0.02, False, False, ECO_TARGET_MISSED),
    (-0.02, False, False, ECO_TARGET_MISSED),
    (0.004, False, True, 0), (-0.004, True, False, 0),  # within MATCH_RTOL (0.5 %)
])
def test_match_trip_time_names_why_it_missed(rel, all_fast, all_slow, want):
    assert int(vel.target_flags(jnp.asarray(rel), jnp.asarray(all_fast),
                                jnp.asarray(all_slow))) == want


def test_overspeed_band_pays_at_level3s_trip_time():
    # the route allows the cruise speed (80 km/h) everywhere: Level 3 cruises at the limit
    vp = VP.replace(v_cruise=80 / 3.6)
    l3 = PROFILE(HILL, vp)
    trip = float(l3.trip_time)
    e_l3 = float(EXACT(HILL, vp, l3.v, 0.0, LAM_B))
    # no band: nothing may be faster than Level 3, so at its trip time the optimum is Level 3's
    _, r0 = MATCH(HILL, vp, trip, LAM_B)
    assert np.max(np.abs(_valid(HILL, r0.profile.v) - _valid(HILL, l3.v))) < 0.5
    # a 5 km/h band above the cruise speed: slower up the hill, faster down, same trip time
    band = 5 / 3.6
    _, r5 = MATCH(HILL, vp, trip, LAM_B, overspeed=band)
    assert int(r5.status) == 0
    assert abs(float(r5.trip_time) / trip - 1) < 5e-3
    v = _valid(HILL, r5.profile.v)
    assert np.max(v) <= 80 / 3.6 + band + 1e-9 and np.max(v) > 80 / 3.6 + 0.5 * band
    assert np.all(v <= _valid(HILL, r5.v_upper) + 1e-9)
    assert v[0] == pytest.approx(float(l3.v[0])) and v[-1] == pytest.approx(
        float(l3.v[n_nodes(HILL) - 1]), abs=1e-6)
    e_0, e_5 = float(r0.energy_J), float(r5.energy_J)
    assert e_5 < 0.98 * min(e_0, e_l3), (e_5, e_0, e_l3)


def test_strategy_step_grid_holds_a_slow_eco_trip():
    """multilevel-eco with a given (small) lambda_t drives slower than Level 3: its step grid is
    sized from its own trip time, computed on the host (`strategies.steps_for_batch`)."""
    from jaxems import strategies as S
    from jaxems.io import load_route
    from jaxems.params import stack_vehicles

    route = load_route("short_track")
    vp = VP.replace(mass=25000.0)
    opts = S.Options(eco_lambda_t=300.0)
    n3 = S.steps_for_batch(route, vp)
    n = S.steps_for_batch(route, vp, 1.0, "multilevel-eco", opts)
    # Level 3's trip and the eco optimum's at lambda_t = 300 J/s (`eco_speed`: Level 3, the
    # charge-sustaining lambda_b, the speed optimisation), by the functions steps_for_batch
    # compiled (compiling them again took half a minute)
    vps = stack_vehicles([vp])
    t3 = float(S._profile_batch(route, vps, jnp.full((1, route.grade.shape[-1]),
                                                     vp.w_pred)).trip_time[0])
    t_eco = float(S.eco_trip_times(route, vps, 1.0, n3, opts)[0])
    assert t_eco > 1.05 * t3  # it is slower
    # with a margin for the run's own optimum, which another program need not land on
    assert n >= (1 + S.ECO_STEPS_MARGIN) * t_eco and n >= n3
