"""Level 2 (jaxems.levels.battery): bisection, I1 battery limits, I2 guards, I3 horizon.

References (`jaxems.reference`, plain NumPy): the gear rule and E_b(t_f)(lambda_b) from a
brute-force search of each mode's Hamiltonian at the step's gear; a NumPy dynamic program over a
fine E_b grid on the same Level 2 model (its own fuel model per mode, written from the paper's
equations) for the fuel; hand-built cases with known minimal switching counts and a brute-force
enumeration for I2b.
"""

from __future__ import annotations

import functools

import jax
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jaxems import powertrain as pt
from jaxems import xla
from jaxems.levels import battery as b
from jaxems.levels.powersplit import mode_gear_split
from jaxems.params import RPM, load_vehicle, stack_vehicles
from jaxems.reference import (_pb_of_pbi, _veh, ref_dp, ref_end, ref_fuel_power, ref_gears,
                               ref_horizon, ref_minimal_switching, ref_paths,
                               ref_steps)

VP = load_vehicle()
W1100 = 1100 * RPM
_steps = xla.jit(b.level2_steps)


def make_route(vp, segs, T=None):
    """segs: [(steps, speed m/s, grade)] -> P_d, v (constant-speed road load)."""
    v = np.concatenate([np.full(n, s, float) for n, s, _ in segs])
    g = np.concatenate([np.full(n, gr, float) for n, _, gr in segs])
    if T is not None:
        v, g = v[:T], g[:T]
    return np.asarray(pt.road_load(vp, v, g)) * v, v


# -------------------------------------------------------------------------------- kernels
_pass = xla.jit(b.table_pass)
_table = xla.jit(b.step_table)
_mgs_steps = xla.jit(jax.vmap(mode_gear_split, in_axes=(None, 0, 0, 0)))


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**16), conventional=st.booleans())
def test_level2_steps_are_the_full_tables_best_mode_at_the_gear(seed, conventional):
    """Level 2's step (the lambda-free part tabled once, `step_table`) against the minimum of
    `mode_gear_split` (every candidate evaluated at the costate) over the modes at the step's
    gear, and against the NumPy brute force (`reference.ref_steps`); costates either side of
    zero, a truck with and without a motor."""
    rng = np.random.default_rng(seed)
    vp = VP.replace(has_motor=0.0) if conventional else VP
    T = 64
    P_d, v = rng.uniform(-250e3, 400e3, T), rng.uniform(0.0, 27.0, T)
    gear, lam = rng.integers(0, 12, T), rng.uniform(-6.0, 0.5, T)
    ok = rng.random(T) < 0.9
    got = _steps(vp, P_d, v, gear, ok, lam, DT_H)
    sp = _mgs_steps(vp, P_d, v, lam)
    H = np.asarray(sp.H)[np.arange(T), :, gear]  # (T, 4) at the step's gear
    m = np.argmin(H, axis=1)
    use = ok & np.isfinite(H[np.arange(T), m])
    P_b = np.where(use, np.asarray(sp.P_b)[np.arange(T), m, gear], 0.0)
    E_f = np.where(use, np.asarray(sp.P_f)[np.arange(T), m, gear], 0.0) * DT_H
    # a clear best mode (ties at a guard may go either way up to rounding)
    Hs = np.sort(H, axis=1)
    with np.errstate(invalid="ignore"):  # inf - inf where one mode or none is feasible
        clear = ~use | ~(Hs[:, 1] - Hs[:, 0] <= 1e-9 * np.abs(Hs[:, 0]) + 1e-6)
    assert np.sum(clear & use) >= 8  # random gears: many steps have no feasible mode
    np.testing.assert_array_equal(np.asarray(got.mode)[clear & use], m[clear & use])
    np.testing.assert_allclose(np.asarray(got.P_b)[clear], P_b[clear], rtol=1e-12, atol=1e-6)
    np.testing.assert_allclose(np.asarray(got.E_f)[clear], E_f[clear], rtol=1e-12, atol=1e-6)
    np.testing.assert_allclose(np.asarray(got.dE), -np.asarray(pt.battery_internal(
        vp, np.asarray(got.P_b))) * DT_H, rtol=1e-12, atol=1e-6)
    ref = ref_steps(vp, P_d, v, gear, ok, lam, DT_H)
    assert np.all((np.asarray(got.mode) == ref.mode) | ~clear | ~use)
    np.testing.assert_allclose(np.asarray(got.E_f)[clear], ref.E_f[clear], rtol=1e-6, atol=1.0)
    np.testing.assert_allclose(np.asarray(got.dE)[clear], ref.dE[clear], rtol=1e-6, atol=1.0)
    # a bisection's pass reads the table: the same dE and E_f (another program: up to an ulp)
    dE, E_f = _pass(vp, _table(vp, P_d, v, gear), ok, lam, DT_H)
    np.testing.assert_allclose(np.asarray(dE), np.asarray(got.dE), rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(np.asarray(E_f), np.asarray(got.E_f), rtol=1e-12, atol=1e-9)


@settings(max_examples=20, deadline=None)
@given(j=st.integers(0, 110), seed=st.integers(0, 2**16))
def test_gears_of_a_window_are_the_routes_sliced(j, seed):
    """The gear rule and the step table are step by step, so a receding horizon may slice the
    whole route's (`strategies.MpcParams.gears`); and the kernels given those give the same
    result. The kernels read a given (gear, ok) pair through `step_model` (the step table on
    it), so the sliced pair's model is the sliced route's model, and the kernels are run with
    that model (a run with the pair too compiled both kernels again for no other path).
    (One window length: each new shape would compile the kernels again.)"""
    rng = np.random.default_rng(seed)
    T, n = 150, 40
    P_d, v = rng.uniform(-150e3, 350e3, T), rng.uniform(0.0, 25.0, T)
    w, mask = rng.uniform(600, 1800, T) * RPM, rng.random(T) < 0.9
    gear, ok = _gears(VP, P_d, v, w, mask)
    sl = slice(j, j + n)
    window = (VP, P_d[sl], v[sl], w[sl], mask[sl])
    g_w, ok_w = _gears(*window)
    np.testing.assert_array_equal(np.asarray(gear)[sl], np.asarray(g_w))
    np.testing.assert_array_equal(np.asarray(ok)[sl], np.asarray(ok_w))
    args = (*window, 1.0, 0.5 * VP.E_b_max)
    given_g = (np.asarray(gear)[sl], np.asarray(ok)[sl])
    # the route's step model (gears and the lambda-free table, `step_model`), sliced: the
    # window's model, and the model the kernels make of the sliced pair
    given_m = jax.tree.map(lambda a: np.asarray(a)[sl], _model(VP, P_d, v, w, mask))
    for a, b_ in ((_model(*window), given_m), (_model(*window, gears=given_g), given_m),
                  (_horizon(*args), _horizon(*args, gears=given_m)),
                  (_costate(*args), _costate(*args, gears=given_m))):
        for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b_), strict=True):
            x, y = np.asarray(x), np.asarray(y)
            if np.issubdtype(x.dtype, np.floating):  # equal on a CPU; a GPU's two programs
                np.testing.assert_allclose(x, y, rtol=1e-12, atol=0)  # round apart (1 ulp)
            else:
                np.testing.assert_array_equal(x, y)


@settings(max_examples=15, deadline=None)
@given(j=st.integers(0, 110), seed=st.integers(0, 2**16), E0=st.floats(0.05, 0.95))
def test_a_window_padded_with_masked_steps_gives_the_same_costate(j, seed, E0):
    """The kernels solve on their steps rounded up to a multiple of 16, the steps beyond them
    masked (`battery.aligned_steps`, for XLA's CPU cumulative sums): a masked step moves no
    energy, so a window given with masked steps up to that length gives the window's costate
    and battery path, bit for bit, and the path stays where the window ends."""
    rng = np.random.default_rng(seed)
    T, n = 170, 40
    n2 = b.aligned_steps(n)
    assert n2 % 16 == 0 and n <= n2 < n + 16
    P_d, v = rng.uniform(-150e3, 350e3, T), rng.uniform(0.0, 25.0, T)
    w, mask = rng.uniform(600, 1800, T) * RPM, rng.random(T) < 0.9
    model = jax.tree.map(np.asarray, _model(VP, P_d, v, w, mask))
    E_b0 = E0 * VP.E_b_max

    def window(m):  # the arrays of an m-step slice at j, masked beyond n
        sl = slice(j, j + m)
        inside = np.arange(m) < n
        gear, ok, tab = jax.tree.map(lambda a: a[sl], model)
        return ((VP, P_d[sl], v[sl], w[sl], mask[sl] & inside, 1.0, E_b0),
                b.StepModel(gear, ok & inside, tab))

    def same(x, y):  # equal on a CPU; a GPU's two programs may round apart (1 ulp)
        x, y = np.asarray(x), np.asarray(y)
        if jax.default_backend() == "cpu" or not np.issubdtype(x.dtype, np.floating):
            np.testing.assert_array_equal(x, y)
        else:
            np.testing.assert_allclose(x, y, rtol=1e-12, atol=0)

    (a, ga), (p, gp) = window(n), window(n2)
    h, hp = _horizon(*a, gears=ga), _horizon(*p, gears=gp)
    for x, y in ((h.lam, hp.lam), (h.status, hp.status), (h.margin, hp.margin)):
        same(x, y)
    c, cp = _costate(*a, gears=ga), _costate(*p, gears=gp)
    for x, y in ((c.lam0, cp.lam0), (c.status, cp.status), (c.lam, np.asarray(cp.lam)[:n]),
                 (c.E_b, np.asarray(cp.E_b)[:n + 1])):
        same(x, y)
    same(np.asarray(cp.E_b)[n:], np.full(n2 - n + 1, np.asarray(c.E_b)[-1]))


@settings(max_examples=30, deadline=None)
@given(K=st.integers(1, 6), seed=st.integers(0, 2**16))
def test_piece_sums_equal_a_loop_over_the_pieces(K, seed):
    """`piece_ids` and `piece_sums` (a cumulative sum's differences, fixed order) against
    loops over the steps; empty pieces sum to 0. One length T: each shape compiles once per
    K."""
    rng = np.random.default_rng(seed)
    T = 64
    bnd = np.sort(np.concatenate([[0], rng.integers(0, T + 1, K - 1), [T]]))
    x = rng.normal(0.0, 1e5, T)
    pid = np.asarray(b.piece_ids(bnd, T))
    # each step's piece, by a loop: the last whose start is at or before it (empty pieces,
    # repeated boundaries, hold no step)
    for j in range(T):
        p = max(q for q in range(K) if bnd[q] <= j)
        assert pid[j] == p and bnd[p] <= j < bnd[p + 1], (j, pid[j], bnd)
    want = np.zeros(K)
    for j in range(T):
        want[pid[j]] += x[j]
    got = np.asarray(_piece_sums(x, pid, K))
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12 * np.abs(x).sum())
    assert np.all(got[np.diff(bnd) == 0] == 0.0)


_piece_sums = xla.jit(b.piece_sums, static_argnums=2)
_gears = xla.jit(b.select_gears)
_model = xla.jit(b.step_model)
_horizon = xla.jit(functools.partial(b.horizon_kernel, n_iter=20, max_pieces=2))
_costate = xla.jit(functools.partial(b.costate_kernel, n_iter=20, max_pieces=2))


def test_gear_rule_matches_reference():
    P_d, v = make_route(VP, [(40, 3.0, 0.0), (40, 12.0, 0.03), (40, 22.0, -0.02)])
    w = np.linspace(700, 1700, T_H) * RPM
    gear, ok = xla.jit(b.select_gears)(VP, P_d, v, w, np.ones(T_H, bool))
    np.testing.assert_array_equal(np.asarray(gear), ref_gears(VP, P_d, v, w))
    assert bool(np.all(ok))


# ------------------------------------------------------------------------------ bisection
T_H = 120  # one horizon length for every test: one compilation per kernel
DT_H = 2.0


@st.composite
def routes(draw):
    n_seg = draw(st.integers(1, 4))
    cuts = sorted(draw(st.lists(st.integers(1, T_H - 1), min_size=n_seg - 1,
                                max_size=n_seg - 1, unique=True)))
    bounds = [0, *cuts, T_H]
    segs = [(bounds[i + 1] - bounds[i], draw(st.floats(6.0, 24.0)),
             draw(st.floats(-0.04, 0.06))) for i in range(n_seg)]
    E0 = draw(st.floats(0.1, 0.9)) * float(VP.E_b_max)
    return segs, E0


@settings(max_examples=15)
@given(routes())
def test_bisection_charge_sustaining_or_infeasible(case):
    segs, E0 = case
    P_d, v = make_route(VP, segs)
    w = np.full(T_H, W1100)
    r = b.bisect_costate(VP, P_d, v, w, None, DT_H, E0)
    tol = 1e-3 * float(VP.E_b_max)
    status = int(r.status)
    assert not status & b.STEP_INFEASIBLE
    lo, hi = float(r.lam_lo[0]), float(r.lam_hi[0])
    if status & b.INFEASIBLE:
        # no costate in the bracket reaches the target (reference loop at the bracket ends)
        e_lo = ref_end(VP, P_d, v, w, b.LAM_BRACKET[0], DT_H, E0)
        e_hi = ref_end(VP, P_d, v, w, b.LAM_BRACKET[1], DT_H, E0)
        assert E0 > e_lo + tol or E0 < e_hi - tol
    else:
        assert abs(float(r.E_b[-1]) - E0) <= tol
        assert abs(float(r.E_b_i2a[-1]) - E0) <= tol
        # the final bracket holds the target in the reference model
        assert ref_end(VP, P_d, v, w, lo, DT_H, E0) >= E0 - tol
        assert ref_end(VP, P_d, v, w, hi, DT_H, E0) <= E0 + tol
        assert hi - lo < 1e-9


def test_monotone_in_costate():
    P_d, v = make_route(VP, [(40, 15, 0.0), (40, 20, 0.04), (40, 18, -0.03)])
    gear, ok = b.select_gears(VP, P_d, v, np.full(T_H, W1100), np.ones(T_H, bool))
    ends = [float(_steps(VP, P_d, v, gear, ok, lam, DT_H).dE.sum())
            for lam in np.linspace(-4, -1, 41)]
    assert np.all(np.diff(ends) <= 1e-6)


def test_climb_beyond_the_battery_is_infeasible():
    # 300 kW up a long climb at 12 m/s: beyond the engine, the motor has to help all the way
    T = T_H
    v = np.full(T, 12.0)
    P_d = np.full(T, 420e3)
    w = np.full(T, W1100)
    r = b.bisect_costate(VP, P_d, v, w, None, DT_H)
    assert int(r.status) & b.INFEASIBLE
    assert float(r.E_b[-1]) < float(VP.E_b0) - 1e-3 * float(VP.E_b_max)
    # with the limits on, E_b would have to leave [0, E_b_max]: also infeasible
    r2 = b.solve_costate(VP, P_d, v, w, None, DT_H)
    assert int(r2.status) & b.INFEASIBLE


# --------------------------------------------------------------------------- I1 and the DP
VP_SMALL = VP.replace(E_b_max=1.0e6)
LIM_SEGS = [(20, 15, 0.0), (27, 15, 0.035), (20, 18, 0.0), (27, 18, -0.03), (26, 15, 0.0)]


def test_limits_piecewise_matches_dp():
    dt = 3.0
    P_d, v = make_route(VP_SMALL, LIM_SEGS)
    w = np.full(len(v), W1100)
    free = b.bisect_costate(VP_SMALL, P_d, v, w, None, dt)
    assert float(free.E_b.min()) < -0.1e6 or float(free.E_b.max()) > 1.1e6  # limits matter
    r = b.solve_costate(VP_SMALL, P_d, v, w, None, dt)
    status = int(r.status)
    assert not status & (b.INFEASIBLE | b.PIECES_EXHAUSTED), b.status_names(status)
    assert int(r.n_pieces) > 1
    E = np.asarray(r.E_b)
    tol = 1e-3 * 1e6
    assert E.min() >= -10.0 and E.max() <= 1e6 + 10.0  # limits within 1e-5 E_b_max
    assert abs(E[-1] - E[0]) <= tol
    # the costate only changes at piece boundaries
    lam = np.asarray(r.lam)
    assert np.count_nonzero(np.diff(lam)) <= int(r.n_pieces) - 1
    dp = ref_dp(VP_SMALL, P_d, v, w, dt, 0.5e6, 0.0, 1e6, n_grid=241)
    fuel = float(r.fuel)
    assert abs(fuel - dp) / dp < 5e-3, (fuel, dp)


@settings(max_examples=6, deadline=None)
@given(speeds=st.lists(st.floats(12.0, 22.0), min_size=5, max_size=5),
       grades=st.lists(st.floats(-0.045, 0.045), min_size=5, max_size=5),
       soc0=st.floats(0.2, 0.8))
def test_limits_solution_is_feasible_and_the_dps_on_random_hills(speeds, grades, soc0):
    """Level 2 with the battery's limits (I1: pieces split where the path leaves them, each at
    its own costate, I2b at guards, a saturated piece held at E_max) on random climbs and
    descents at constant speeds, from random starting charges. Its schedule is what the
    reference's physics gives: each step's two trajectories (B+, B-) re-evaluated with the
    NumPy fuel model (`ref_fuel_power`) at their battery powers, the path summed from the
    selector and held at E_max only in saturated pieces, within the limits, charge
    sustaining; and its fuel is no more than the fuel-optimal DP's over an E_b grid
    (`reference.ref_dp`, one battery power a step; on a flat and a descent that fills the
    battery, 20 t, 1 MJ: Level 2 8.255 MJ, its schedule re-evaluated above; the DP 8.312 /
    8.300 / 8.294 MJ at 241 / 961 / 3841 points), nor less than the DP's relaxation that
    shares a step between two battery powers as Level 2's mix does (`shared=True`: no
    schedule of Level 2's beats it) but for 0.5 % and the grid's error, bounded by the
    cost-to-go's steepest slope (the end penalty's 6) times the grid's spacing: on a route of
    descents that burns 1.23 MJ Level 2 lies 5.2 % below the DP, 1.4 % (18 kJ) below the
    relaxation at 241 points and 0.4 % at 961 (`experiments/level2_hills.py --seed 11`,
    route 246). The fixed route above was the only comparison with the DP; its segment
    lengths are kept, so one compilation serves every example."""
    dt = 3.0
    segs = [(n, s, g) for (n, _, _), s, g in zip(LIM_SEGS, speeds, grades, strict=True)]
    P_d, v = make_route(VP_SMALL, segs)
    w = np.full(len(v), W1100)
    E0, E_max = soc0 * 1e6, 1e6
    r = b.solve_costate(VP_SMALL, P_d, v, w, None, dt, E_b0=E0)
    status = int(r.status)
    if status & b.INFEASIBLE:  # no path within the limits (a climb beyond the battery)
        return
    assert not status & b.PIECES_EXHAUSTED, b.status_names(status)
    gears = ref_gears(VP_SMALL, P_d, v, w)
    np.testing.assert_array_equal(np.asarray(r.gear), gears)
    f = _veh(VP_SMALL)
    wk = np.asarray(VP_SMALL.gear_ratio)[gears] * float(VP_SMALL.r_d) * v
    sel, fuel, E = np.asarray(r.sel), 0.0, [E0]
    pid = np.asarray(b.piece_ids(np.asarray(r.boundaries), len(v)))
    sat = np.asarray(r.saturated)[pid]
    cur = E0
    for k in range(len(v)):
        if k > 0 and pid[k] != pid[k - 1]:  # a piece starts at its boundary value, where the
            cur = float(r.E_bnd[pid[k]])  # last one ended to within its tolerance
            assert abs(E[-1] - cur) <= 1e-3 * E_max
        f_k = []
        for dE, E_f in ((r.dE_plus[k], r.E_f_plus[k]), (r.dE_minus[k], r.E_f_minus[k])):
            P_b = _pb_of_pbi(f, -float(dE) / dt)  # from the internal power (eq. 7)
            f_k.append(float(ref_fuel_power(VP_SMALL, P_d[k], wk[k], gears[k],
                                            np.array([P_b]))[0]) * dt)
            assert f_k[-1] == pytest.approx(float(E_f), rel=1e-9, abs=1e-3), k
        fuel += sel[k] * f_k[0] + (1.0 - sel[k]) * f_k[1]
        cur += sel[k] * float(r.dE_plus[k]) + (1.0 - sel[k]) * float(r.dE_minus[k])
        cur = min(cur, E_max) if sat[k] else cur
        E.append(cur)
    assert fuel == pytest.approx(float(r.fuel), rel=1e-9)
    np.testing.assert_allclose(np.asarray(r.E_b), E, rtol=0, atol=1e-3)
    assert min(E) >= -10.0 and max(E) <= E_max + 10.0 and abs(E[-1] - E0) <= 1e-3 * E_max
    dp, relaxed = (ref_dp(VP_SMALL, P_d, v, w, dt, E0, 0.0, E_max, n_grid=241, shared=shared)
                   for shared in (False, True))
    fuel = float(r.fuel)
    assert relaxed * (1 - 5e-3) - 6.0 * E_max / 240 <= fuel <= dp * (1 + 1e-3), (
        fuel, dp, relaxed, b.status_names(status))


@pytest.mark.parametrize("speeds, grades, soc0", [
    ([12.0, 12.0, 12.0, 12.0, 17.0], [0.0, -0.03125, 0.0, 0.0, -0.0078125], 0.5),  # SEED=99
    ([12.0, 12.0, 12.0, 15.0, 12.0], [0.0, -0.03125, 0.03125, 0.0, 0.0], 0.5),  # SEED=8
    ([17.1, 13.1, 17.6, 19.7, 19.3], [-0.022, 0.044, 0.02, -0.007, -0.008], 0.67),  # +42 %
    ([17.5, 18.2, 14.0, 13.5, 12.1], [0.03, -0.045, -0.022, 0.008, 0.0], 0.74),  # +28 %
    ([20.1, 16.2, 12.9, 14.5, 17.3], [-0.026, 0.021, -0.021, -0.006, -0.009], 0.79),  # +66 %
    ([19.9, 12.8, 20.2, 21.0, 14.5], [-0.024, 0.034, -0.008, -0.009, 0.008], 0.53),  # +31 %
    ([16.0, 13.0, 21.7, 14.2, 18.7], [-0.018, 0.034, 0.015, -0.033, 0.031], 0.77),
    ([17.2, 18.3, 17.4, 16.0, 19.9], [0.034, -0.029, -0.033, -0.035, 0.043], 0.77),
])
def test_limits_around_recuperation_that_fills_the_battery(speeds, grades, soc0):
    """Level 2 where descents fill the 1 MJ battery whatever lambda_b (saturated pieces),
    against the fuel-optimal DP, as the random-hills test checks it. Found by random-seed runs
    (`make test-random SEED=99`, `SEED=8`) and a scan of 1400 random hills (seeds 7 and 11,
    848 with a path within the limits; `docs/results_notes.md`, "Level 2 around recuperation
    that fills the battery"). I1 split a saturated piece where its path left E_max; where
    the path held E_max before or after the free recuperation (a flat or a climb charged or
    idle at the piece's costate), the battery was not spent where the descent would refill it,
    or was spent late: 25 of the 848 burnt more than the DP, up to +66 % (the comments give
    each case's excess). In the first case the path without limits peaks at the descent's
    end (step 47), but the piece's path held E_max through the flats, charging on the engine,
    to step 94: 10.44 MJ against the DP's 9.11 MJ; in the second it held E_max up the climb
    after the descent: 31.85 against 23.89 MJ. I1 now splits at the end of the free charge
    (`_solve_pieces`' `over`), and all 848 lie within the DP's bounds. The last two cases
    held E_max on climbs before the descent (+3.0 %, +2.6 %) with a split counted only where
    the engine's charge was dumped after the recuperation."""
    test_limits_solution_is_feasible_and_the_dps_on_random_hills.hypothesis.inner_test(
        speeds=speeds, grades=grades, soc0=soc0)


def test_limits_solution_does_not_depend_on_the_piece_budget():
    """I1 splits every violating piece per round; pieces are independent between their
    boundaries, so any budget that suffices gives the same pieces, costate and path; a budget
    that does not is flagged."""
    dt = 3.0
    P_d, v = make_route(VP_SMALL, LIM_SEGS)
    w = np.full(len(v), W1100)
    r16 = b.solve_costate(VP_SMALL, P_d, v, w, None, dt, max_pieces=16)
    n = int(r16.n_pieces)
    assert n >= 3 and not int(r16.status) & b.PIECES_EXHAUSTED
    r_n = b.solve_costate(VP_SMALL, P_d, v, w, None, dt, max_pieces=n)
    assert int(r_n.n_pieces) == n and int(r_n.status) == int(r16.status)
    np.testing.assert_array_equal(np.asarray(r_n.boundaries)[: n + 1],
                                  np.asarray(r16.boundaries)[: n + 1])
    for name in ("lam", "E_b", "fuel"):
        np.testing.assert_allclose(np.asarray(getattr(r_n, name)),
                                   np.asarray(getattr(r16, name)), rtol=1e-12, atol=1e-6)
    short = b.solve_costate(VP_SMALL, P_d, v, w, None, dt, max_pieces=n - 1)
    assert int(short.status) & b.PIECES_EXHAUSTED


# ------------------------------------------------------------------------------------- I2
def test_minimal_switching_known_cases():
    T = 100
    up, dn = np.ones(T), -np.ones(T)
    # one switch: up to the top then down (or down then up)
    s = b.minimal_switching(up, dn, 50.0, 50.0, 0.0, 100.0, 1e-9)
    assert bool(s.feasible) and int(s.n_switches) == 1
    assert abs(float(s.E_b[-1]) - 50.0) < 1e-6
    # E_max at 80: going down first is the one-switch answer
    s = b.minimal_switching(up, dn, 50.0, 50.0, 0.0, 80.0, 1e-9)
    assert int(s.n_switches) == 1 and float(s.E_b.min()) >= -1e-6
    assert float(s.E_b.max()) <= 80 + 1e-6
    # limits [20, 80]: no single switch works (it would reach 0 or 100): two switches
    s = b.minimal_switching(up, dn, 50.0, 50.0, 20.0, 80.0, 1e-9)
    assert bool(s.feasible) and int(s.n_switches) == 2
    E = np.asarray(s.E_b)
    assert E.min() >= 20 - 1e-6 and E.max() <= 80 + 1e-6 and abs(E[-1] - 50) < 1e-6
    # a switch advanced so that the limit is just touched (Figure 15): E_b reaches E_min
    assert abs(E.min() - 20) < 1e-6
    # impossible, from a start within the limits: the end out of reach (both trajectories
    # charge, at least +50 over the window, where the end asks for 0)
    s = b.minimal_switching(up, 0.5 * up, 50.0, 50.0, 0.0, 200.0, 1e-9)
    assert not bool(s.feasible)
    # the end within reach (-50 forced, then up to +50), but both trajectories discharge 50
    # first, which from 20 crosses the lower limit
    forced = np.where(np.arange(T) < 50, -1.0, 1.0)
    s = b.minimal_switching(forced, dn, 20.0, 20.0, 0.0, 100.0, 1e-9)
    assert not bool(s.feasible)
    # the same from 60: it reaches 10 and back (one switch or none: the end is B+'s own)
    s = b.minimal_switching(forced, dn, 60.0, 60.0, 0.0, 100.0, 1e-9)
    assert bool(s.feasible) and abs(float(s.E_b[-1]) - 60.0) < 1e-6
    assert float(np.min(s.E_b)) >= -1e-6


@settings(max_examples=30, deadline=None)
@given(st.lists(st.integers(-2, 2), min_size=12, max_size=12),
       st.lists(st.integers(0, 4), min_size=12, max_size=12),
       st.sampled_from([3.0, 4.0, 10.0]), st.integers(0, 10), st.integers(-3, 3))
def test_minimal_switching_vs_brute_force(base, gap, hi_lim, e0, de):
    # against every set of switching steps, each with its fraction free (the switch falls
    # inside the step, as the kernel places it): the same feasibility, the same fewest
    # switches (the narrow bands need up to five; 200-400 scratch draws per band all agreed)
    lo_lim = 0.0
    e0 = min(e0, int(hi_lim))
    dm = np.array(base, float)
    dp = dm + np.array(gap, float)
    end = float(e0 + de)
    ok, best = ref_minimal_switching(dp, dm, float(e0), end, lo_lim, hi_lim)
    r = b.minimal_switching(dp, dm, float(e0), end, lo_lim, hi_lim, 1e-9)
    assert bool(r.feasible) == ok
    if ok:
        E = np.asarray(r.E_b)
        sel = np.asarray(r.sel)
        assert np.all((sel >= 0.0) & (sel <= 1.0))
        np.testing.assert_allclose(E, e0 + np.concatenate([[0.0], np.cumsum(
            sel * dp + (1 - sel) * dm)]), atol=1e-9)
        # within the limits up to the end, which is on its value: the end value stands where
        # the caller puts it, beyond a limit too, for the kernel as for the reference (drawn
        # 3 -> 4 J within 0-3 J: feasible to both)
        assert E[:-1].min() >= lo_lim - 1e-6 and E[:-1].max() <= hi_lim + 1e-6
        assert abs(E[-1] - end) < 1e-6
        assert int(r.n_switches) == best


def guard_route():
    T = T_H
    P_d, v = make_route(VP, [(40, 16.7, 0.0), (40, 16.7, 0.01), (40, 16.7, 0.004)])
    return P_d, v, np.full(T, W1100)


def test_guard_mixing_is_charge_sustaining():
    P_d, v, w = guard_route()
    dt = 4.0
    r = b.bisect_costate(VP, P_d, v, w, None, dt)  # one piece, no limits
    assert int(r.status) & b.AT_GUARD, b.status_names(r.status)
    assert not int(r.status) & b.INFEASIBLE
    tol = 1e-3 * float(VP.E_b_max)
    E0 = float(VP.E_b0)
    # neither side of the guard is charge sustaining: E_b(t_f) jumps over the target, also in
    # the reference loop
    assert ref_end(VP, P_d, v, w, float(r.lam_lo[0]), dt, E0) > E0 + 10 * tol
    assert ref_end(VP, P_d, v, w, float(r.lam_hi[0]), dt, E0) < E0 - 10 * tol
    # I2a (eq. 55): the ratio puts E_b(t_f) on target
    r_mix = float(r.r_plus[0])
    e_plus = E0 + float(np.sum(r.dE_plus))
    e_minus = E0 + float(np.sum(r.dE_minus))
    assert 0 < r_mix < 1
    assert abs(r_mix * e_plus + (1 - r_mix) * e_minus - E0) <= 1e-6 * tol
    assert abs(float(r.E_b_i2a[-1]) - E0) <= tol
    # I2b without limits: exactly one (back-propagated) switch
    assert abs(float(r.E_b[-1]) - E0) <= tol
    assert int(r.n_switches) == 1
    # at the guard both sides have equal H: I2a and I2b burn the same fuel
    fuel_i2a = r_mix * np.sum(r.E_f_plus) + (1 - r_mix) * np.sum(r.E_f_minus)
    assert abs(float(fuel_i2a) - float(r.fuel)) <= abs(float(r.lam0)) * tol
    # with limits (Figures 14-15), on a constant demand at the guard: B+ charges and B-
    # discharges at every step, so a band of +-5 % around E0 needs several switches
    P_c, v_c = make_route(VP, [(T_H, 16.7, 0.005)])
    rc = b.bisect_costate(VP, P_c, v_c, w, None, dt)
    assert int(rc.status) & b.AT_GUARD
    assert np.all(np.asarray(rc.dE_plus) > 0) and np.all(np.asarray(rc.dE_minus) < 0)
    E_max = float(VP.E_b_max)
    s = b.minimal_switching(rc.dE_plus, rc.dE_minus, E0, E0, 0.45 * E_max, 0.55 * E_max, 1.0)
    E = np.asarray(s.E_b)
    assert bool(s.feasible) and int(s.n_switches) >= 2
    assert E.min() >= 0.45 * E_max - 2.0 and E.max() <= 0.55 * E_max + 2.0  # slack 1 J
    assert abs(E[-1] - E0) <= 2.0


# ----------------------------------------------------------------------------- batching
def test_batch_equals_loop_and_no_retrace():
    P_d, v = make_route(VP, [(40, 15, 0.0), (40, 20, 0.04), (40, 18, -0.03)])
    P_d2, v2 = make_route(VP, [(60, 10, 0.02), (60, 22, -0.01)])
    P3, V3 = np.stack([P_d, P_d2, P_d]), np.stack([v, v2, v])
    W3 = np.full_like(P3, W1100)
    vps = stack_vehicles([VP, VP.replace(mass=30e3), VP.replace(E_b_max=2e6, soc0=0.3)])
    batch = b.costate_batch(vps, P3, V3, W3, None, DT_H)
    singles = [VP, VP.replace(mass=30e3), VP.replace(E_b_max=2e6, soc0=0.3)]
    fields = ("lam", "lam0", "E_b", "status", "n_pieces", "fuel")

    def same(got, one):
        for name in fields:
            np.testing.assert_allclose(np.asarray(getattr(got, name)),
                                       np.asarray(getattr(one, name)), rtol=1e-9, atol=1e-6,
                                       err_msg=name)

    for i, vp in enumerate(singles):
        one = b.solve_costate(vp, P3[i], V3[i], W3[i], None, DT_H)
        same(jax.tree_util.tree_map(lambda x, i=i: x[i], batch), one)
    # routes x vehicles product: every member is its own solve
    prod = b.costate_product(vps, P3[:2], V3[:2], W3[:2], None, DT_H)
    assert prod.lam0.shape == (2, 3)
    for r in range(2):
        for i, vp in enumerate(singles):
            one = b.solve_costate(vp, P3[r], V3[r], W3[r], None, DT_H)
            same(jax.tree_util.tree_map(lambda x, r=r, i=i: x[r, i], prod), one)
    # new values (vehicle, route, start energy) do not recompile, nor do the same values as
    # NumPy scalars instead of (weakly typed) Python floats
    n0 = b._costate_jit._cache_size()
    b.solve_costate(VP.replace(mass=27e3), P_d2 * 0.9, v2, W3[1], None, 3.0, 0.4e6)
    b.solve_costate(VP.replace(mass=27e3), P_d2 * 0.9, v2, W3[1], None, np.float64(3.0),
                    np.float64(0.4e6), E_min=np.float64(0.0), tol_rel=np.float32(1e-3))
    assert b._costate_jit._cache_size() == n0


def test_input_validation():
    P_d, v = make_route(VP, [(10, 15, 0.0)])
    w = np.full(10, W1100)
    with pytest.raises(ValueError, match="dt"):
        b.solve_costate(VP, P_d, v, w, None, 0.0)
    with pytest.raises(ValueError, match="v: shape"):
        b.solve_costate(VP, P_d, v[:5], w)
    with pytest.raises(ValueError, match="E_b0"):
        b.solve_costate(VP, P_d, v, w, None, 1.0, E_b0=5e6)


# ------------------------------------------------------------------------------------- I3
def test_horizon_maximises_margin():
    P_d, v = make_route(VP, [(60, 16.7, 0.01), (60, 16.7, -0.005)])
    w = np.full(T_H, W1100)
    E0, E_max = 2.0e6, float(VP.E_b_max)
    h = b.level2_horizon(VP, P_d, v, w, None, DT_H, E0)
    assert not int(h.status) & b.I3A, b.status_names(h.status)
    gear, ok = b.select_gears(VP, P_d, v, w, np.ones(T_H, bool))
    gear, ok = np.asarray(gear), np.asarray(ok)
    # grid search over constant costates (NumPy)
    E = ref_paths(VP, P_d, v, gear, ok, np.linspace(-6, -0.3, 300), DT_H, E0)
    best = np.max(np.minimum(E.min(axis=1), E_max - E.max(axis=1)))
    assert float(h.margin) >= best - 1e-6 * E_max
    E = np.asarray(h.E_b)
    assert abs(min(E.min(), E_max - E.max()) - float(h.margin)) < 1e-6 * E_max


def test_horizon_event_I3a():
    # a long descent fills the battery whatever lambda_b: the first sub-problem ends on E_max
    P_d, v = make_route(VP_SMALL, [(40, 15, 0.01), (40, 18, -0.05), (40, 16, 0.0)])
    w = np.full(T_H, W1100)
    h = b.level2_horizon(VP_SMALL, P_d, v, w, None, DT_H, 0.5e6)
    assert int(h.status) & b.I3A, b.status_names(h.status)
    assert 40 <= int(h.t_event) <= 80
    E = np.asarray(h.E_b)
    assert abs(E[int(h.t_event)] - 1e6) <= 1e-3 * 1e6
    assert E[: int(h.t_event) + 1].max() <= 1e6 + 1.0


@pytest.mark.parametrize("v1, g1, g2, E0, E_max", [
    (10.0, -0.01, -0.05, 2e5, 1e6),  # a descent fills the battery whatever lambda_b
    (10.0, 0.0, -0.02, 2e5, 1e6),  # at a guard, the two limits crossed alike (a tie)
    (20.0, 0.0, -0.05, 2e5, 1e6),
    (10.0, 0.02, -0.02, 8e5, 1e6),
    (16.7, 0.01, -0.01, 2e6, 4e6),  # no event: the climb and the descent fit a 4 MJ battery
])
def test_horizon_equals_its_loop_and_its_event_ends_on_the_limit(v1, g1, g2, E0, E_max):
    """I3 against its loops (`reference.ref_horizon`): the margin of the mixed paths, and
    whether a limit is crossed whatever lambda_b (I3a); no costate and mix on a grid (pairs of
    neighbouring costates, the mix in steps of 1/40) keeps the battery farther from its
    limits. Under I3a the event is the largest violation of the mixed paths, and the first
    sub-problem's path stays within the limits up to it and ends on the limit crossed there.
    At a guard the mix balances a violation of each limit, so that two events tie and
    rounding picks one: either is an event (the first sub-problem, with I1 inside, holds the
    limits before it)."""
    vp = VP.replace(E_b_max=E_max)
    P_d, v = make_route(vp, [(40, v1, g1), (40, 18.0, g2), (40, 16.0, 0.0)])
    w = np.full(T_H, W1100)
    h = b.level2_horizon(vp, P_d, v, w, None, DT_H, E0)
    gear, ok = (np.asarray(x) for x in b.select_gears(vp, P_d, v, w, np.ones(T_H, bool)))
    want = ref_horizon(vp, P_d, v, gear, ok, DT_H, E0, 0.0, E_max, 1e-6 * E_max)
    assert float(h.margin) == pytest.approx(want.margin, abs=1e-6 * E_max)
    assert bool(int(h.status) & b.I3A) == want.event == (E_max < 2e6)
    # the grid: the mix of each two neighbouring costates' paths at every fraction
    paths = ref_paths(vp, P_d, v, gear, ok, np.linspace(-6.0, -0.3, 80), DT_H, E0)
    r = np.linspace(0.0, 1.0, 41)[:, None, None]
    mixes = paths[1:][None] + r * (paths[:-1] - paths[1:])[None]
    grid = np.max(np.minimum(mixes.min(axis=-1), E_max - mixes.max(axis=-1)))
    assert float(h.margin) >= grid - 1e-6 * E_max
    if not want.event:
        assert int(h.t_event) == T_H
        np.testing.assert_allclose(np.asarray(h.E_b), want.E_mix, atol=1e-3 * E_max)
        return
    viol = np.maximum(np.maximum(want.E_mix - E_max, -want.E_mix), 0.0)
    te = int(h.t_event)
    assert viol[te] >= viol.max() - 1e-3 * E_max
    E = np.asarray(h.E_b)[: te + 1]
    assert E[-1] == pytest.approx(E_max if want.E_mix[te] > E_max else 0.0, abs=1e-3 * E_max)
    assert E.min() >= -1e-3 * E_max and E.max() <= E_max * (1 + 1e-3)


def test_horizon_on_guard_I3b():
    # constant demand on a guard: the two solutions run to either limit, lambda_b is the guard
    P_d, v = make_route(VP, [(T_H, 16.7, 0.005)])
    w = np.full(T_H, W1100)
    h = b.level2_horizon(VP, P_d, v, w, None, DT_H, 2.0e6)
    assert int(h.status) & b.I3B and int(h.status) & b.AT_GUARD, b.status_names(h.status)
    assert float(h.lam_hi) - float(h.lam_lo) < 1e-9
    # the guard itself: just below it E_b(t_f) is high, just above it low (reference loop)
    e_lo = ref_end(VP, P_d, v, w, float(h.lam_lo) - 1e-6, DT_H, 2.0e6)
    e_hi = ref_end(VP, P_d, v, w, float(h.lam_hi) + 1e-6, DT_H, 2.0e6)
    assert e_lo >= float(VP.E_b_max) and e_hi <= 0.0
    # the balanced mix keeps E_b mid-range
    assert abs(float(h.margin) - 2.0e6) < 1e-3 * float(VP.E_b_max)


@settings(max_examples=30)
@given(guard=st.floats(-5.5, -0.5), shift_ulps=st.integers(-3000, 3000),
       dtype=st.sampled_from(["float32", "float64"]))
def test_bracket_held_puts_the_ends_back_on_their_sides(guard, shift_ulps, dtype):
    """`bracket_held`: a bisection's ends evaluated again where a tie rounds otherwise (here a
    step in the end value whose place moves by shift_ulps between the loop and the second
    evaluation) move outward until they lie on the sides the loop left them; ends that hold,
    and ends the loop never moved, stay as they are, to the bit."""
    import jax.numpy as jnp

    from jaxems.levels.battery import bracket_held

    dt_ = jnp.dtype(dtype)
    lam_lo, lam_hi = jnp.asarray(-6.0, dt_), jnp.asarray(-0.3, dt_)
    # three pieces: a guard inside the bracket, and two whose target no costate reaches
    guards = jnp.asarray([guard, -7.0, 1.0], dt_)

    def end_value(lam, g):  # 1 (too much left) below the guard, 0 from it on
        return jnp.where(lam < g, 1.0, 0.0).astype(dt_)

    up = lambda e: e > 0.5  # noqa: E731
    lo, hi = jnp.full(3, lam_lo), jnp.full(3, lam_hi)
    for _ in range(80):  # the loop's bisection, on the true guard
        mid = 0.5 * (lo + hi)
        u = up(end_value(mid, guards))
        lo, hi = jnp.where(u, mid, lo), jnp.where(u, hi, mid)
    ulp = float(jnp.finfo(dt_).eps) * abs(guard)
    moved = guards + jnp.asarray([shift_ulps * ulp, 0.0, 0.0], dt_)

    def ends(lo, hi):  # the second evaluation, its step moved
        return end_value(lo, moved), end_value(hi, moved)

    lo2, hi2, (e_lo, e_hi) = bracket_held(ends, up, lo, hi, lam_lo, lam_hi, lambda o: o)
    assert bool(up(e_lo[0])) and not bool(up(e_hi[0]))
    assert float(lo2[0]) <= float(lo[0]) and float(hi2[0]) >= float(hi[0])
    # within the step that reaches the moved guard (16 ulps, times 4 a round)
    assert float(hi2[0] - lo2[0]) <= 4 * abs(shift_ulps) * ulp + 64 * ulp + float(hi[0] - lo[0])
    if lo[0] < moved[0] <= hi[0]:  # the loop's ends hold: nothing moves
        assert float(lo2[0]) == float(lo[0]) and float(hi2[0]) == float(hi[0])
    # pieces whose ends the loop never moved (no costate reaches their target) stay
    np.testing.assert_array_equal(np.asarray(lo2[1:]), np.asarray(lo[1:]))
    np.testing.assert_array_equal(np.asarray(hi2[1:]), np.asarray(hi[1:]))
