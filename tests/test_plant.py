"""Plant: energy balance, stops, battery limits, open driveline, vmap == loop, the scan equal to
its loop (`reference.ref_plant`)."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from jaxems import plant as P
from jaxems import powertrain as pt
from jaxems import reference as R
from jaxems import strategies as S
from jaxems import xla
from jaxems.levels import powersplit as ps
from jaxems.levels.velocity import V_CRAWL, predict_velocity
from jaxems.params import load_vehicle, vehicle_axes
from jaxems.route import Row, route_from_rows

import trace_checks

ROWS = [
    Row(0, 0, 0.0, 5), Row(0.001, 40, 0.0, 0), Row(300, 40, 5.0, 0), Row(500, 40, 0.0, 0),
    Row(600, 40, -6.0, 0), Row(700, 40, 0.0, 0), Row(800, 0, 0.0, 10), Row(800.001, 50, 1.0, 0),
    Row(1200, 0, 1.0, 2),
]
ROUTE = route_from_rows([r._replace(line=i + 2) for i, r in enumerate(ROWS)], ds=10.0,
                        bucket=64)
# a launch at the foot of a 30 % climb: the same shapes as ROUTE (one compilation for both)
STEEP = route_from_rows([r._replace(line=i + 2) for i, r in enumerate([
    Row(0, 0, 0.0, 5), Row(0.001, 30, 30.0, 0), Row(150, 30, 0.0, 0), Row(400, 0, 0.0, 2)])],
    ds=10.0, bucket=64)
VP = load_vehicle()
PRED = PRED_STEEP = None  # Level 3 on ROUTE, STEEP: set by the module fixture `_prediction`
N_PLANT = 320


def truck(hybrid, **fields):
    """VP with these fields replaced, the hybrid or its conventional truck (no motor)."""
    vp = VP.replace(**fields)
    return vp if hybrid else vp.conventional()


@pytest.fixture(scope="module", autouse=True)
def _prediction():
    global PRED, PRED_STEEP
    PRED = predict_velocity(ROUTE, VP, n_steps=256)
    PRED_STEEP = predict_velocity(STEEP, VP, n_steps=256)


def greedy(lam, cstate, vp, obs):
    """The Hamiltonian minimum without switching costs, at the observed demand."""
    tab = ps.mode_gear_split(vp, obs.P_req, obs.v_op, lam)
    H = tab.H.reshape(-1)
    n = vp.gear_ratio.shape[0]
    i = jnp.argmin(H)
    i = jnp.where(jnp.isfinite(H[i]), i, obs.mode * n + obs.gear)
    return cstate, P.Command(mode=i // n, gear=i % n, lam=lam, P_b=jnp.nan)


@xla.jit(static_argnames="end_cap")
def run(vp, lam, end_cap=True):
    track = P.make_track(ROUTE, PRED, end_cap)
    return P.run_plant(vp, track, greedy, lam, jnp.zeros(()), ps.MO, 0, N_PLANT)


# the issue asks the balance to close within 0.1 %; in float64 it closes to rounding, and
# the smallest loss it counts (the clutch's slip, about 7e-4 of the input on the short
# track) would pass unnoticed at 0.1 %: the tests hold it to rounding. What the balance
# checks is the accounting: each loss is a difference of the step's powers (fuel - engine,
# engine - clutch output, battery - motor, ...), so a term left out or counted twice, power
# that reaches the wheels by no counted path, or a step's motion that its wheel power does not
# make breaks it; a wrong model (an efficiency, the fuel map, the slip) does not. The models are
# checked against the plant written as a loop with its own NumPy physics
# (`test_plant_equals_its_loop`: every power of every step and every loss's total) and the
# road work against the route (`test_road_work_is_the_gradient_of_the_distance_covered`)
BALANCE_RTOL = 1e-9


def rel_balance(res, vp):
    e_in, e_out = P.energy_balance(res, vp)
    return float(abs(e_in - e_out) / abs(e_in))


@settings(max_examples=12)
@given(
    mass=st.floats(12e3, 40e3),
    lam=st.floats(-3.5, -1.2),
    battery=st.floats(0.3e6, 6e6),
    hybrid=st.booleans(),
)
def test_energy_balance_closes(mass, lam, battery, hybrid):
    vp = truck(hybrid, mass=mass, E_b_max=battery)
    res = run(vp, lam)
    assert bool(res.final.done)
    assert rel_balance(res, vp) < BALANCE_RTOL
    # each loss is a loss
    t = res.final.tot
    for name in ("loss_engine", "loss_slip", "loss_motor", "loss_battery", "loss_brake",
                 "loss_sync"):
        assert float(getattr(t, name)) >= -1e-6 * float(t.fuel), name
    # battery within its limits throughout
    E = np.asarray(res.trace.E_b)
    assert E.min() >= -1e-6 and E.max() <= battery * (1 + 1e-9)
    assert 0 <= float(res.final.E_b) <= battery * (1 + 1e-9)


def test_stops_are_served_for_their_duration():
    res = run(VP, -2.2)
    s = np.asarray(res.trace.s)
    v = np.asarray(res.trace.v)
    assert bool(res.final.done)
    L = float(ROUTE.length)
    for pos, dur in ((0.0, 5), (800.0, 10)):
        at = (np.abs(s - pos) < 1e-3) & (v == 0)
        assert at.sum() >= dur, (pos, at.sum())
    assert abs(float(res.final.s) - L) < 1e-3
    assert float(res.final.v) == 0.0  # the route ends with a stop
    # never beyond the route, never backwards
    assert np.all(np.diff(s) >= -1e-9) and s.max() <= L + 1e-6


def test_launch_state_engaged_while_standing():
    # the switch out of the open mode falls in the stop's last second: the truck sets off in
    # the step right after the stop's duration, already in a driving state
    res = run(VP, -2.2)
    s = np.asarray(res.trace.s)
    v = np.asarray(res.trace.v)
    mode = np.asarray(res.trace.mode)
    at = np.flatnonzero((np.abs(s - 800.0) < 1e-3) & (v == 0))
    assert at.size > 0 and np.all(np.diff(at) == 1)
    # arrival in step at[0] - 1; the stop's 10 s, counted from the arrival within that step,
    # to the nearest step: standing steps at[0] .. launch - 1; launch in the step after
    assert at.size in (10, 10 + 1), at.size
    launch = at[-1]
    assert v[launch + 1] > 0
    assert mode[launch] != ps.MO and mode[launch - 1] != ps.MO  # engaged in the last second
    assert np.all(mode[at[0]:launch - 1] == ps.MO)


def planned_zero(drive_mode, catch_up, cstate, vp, obs):
    """The greedy gear in drive_mode wherever greedy drives, with a planned battery power of
    0: M_c (the engine drives where it can) or M_m (only the plant's rules make the motor
    recover the reference)."""
    _, cmd = greedy(-2.2, cstate, vp, obs)
    mode = jnp.where(cmd.mode == ps.MO, ps.MO, drive_mode)
    return cstate, cmd._replace(mode=mode, P_b=jnp.zeros(()), catch_up=catch_up)


@xla.jit(static_argnames="drive_mode")
def run_planned(catch_up, drive_mode=ps.MC):
    track = P.make_track(ROUTE, PRED)
    return P.run_plant(VP, track, functools.partial(planned_zero, drive_mode), catch_up,
                       jnp.zeros(()), ps.MO, 0, N_PLANT)


def test_catch_up_on_the_battery_only_when_allowed():
    # recovering the reference after a switch: with the battery (catch_up) it drains more and
    # arrives sooner; without, the battery covers only what the reference's own acceleration
    # needs beyond the engine
    with_b, without = run_planned(True), run_planned(False)
    assert bool(with_b.final.done) and bool(without.final.done)

    def drawn(res):
        return float(np.sum(np.maximum(np.asarray(res.trace.P_b), 0.0)))

    assert drawn(without) < drawn(with_b)
    assert float(without.final.tot.trip_time) >= float(with_b.final.tot.trip_time)
    assert rel_balance(without, VP) < BALANCE_RTOL


def test_motor_alone_recovers_the_reference_whatever_the_plan():
    # with the engine disconnected the battery is all there is: the plant recovers the
    # reference speed after a switch whether or not the controller lets the battery catch up
    # (held at the speed it had, the truck fell behind for good in M_m's crawls); where the
    # engine runs, catch_up decides (test above)
    with_b, without = run_planned(True, ps.MM), run_planned(False, ps.MM)
    mode = np.asarray(without.trace.mode)
    engine = np.flatnonzero((mode == ps.ME) | (mode == ps.MC))
    n = int(engine[0]) if engine.size else N_PLANT
    v_w, v_wo = np.asarray(with_b.trace.v)[:n], np.asarray(without.trace.v)[:n]
    # the prefix in M_m holds switches that lose speed (gear changes while driving)
    gear = np.asarray(without.trace.gear)[:n]
    assert np.sum((np.diff(gear) != 0) & (mode[1:n] == ps.MM)) >= 2
    np.testing.assert_array_equal(v_wo, v_w)
    np.testing.assert_array_equal(np.asarray(without.trace.P_b)[:n],
                                  np.asarray(with_b.trace.P_b)[:n])
    assert rel_balance(without, VP) < BALANCE_RTOL


def fixed_gear(gear, cstate, vp, obs):
    """Always the engine in one gear, whatever the speed (a plan made for another speed)."""
    return cstate, P.Command(mode=ps.ME, gear=gear, lam=-2.2, P_b=jnp.nan)


@xla.jit
def run_fixed_gear(gear):
    track = P.make_track(ROUTE, PRED)
    return P.run_plant(VP, track, fixed_gear, gear, jnp.zeros(()), ps.MO, 0, N_PLANT)


@pytest.mark.parametrize("gear", [5, 9])
def test_protection_keeps_up_with_the_reference(gear):
    # a requested gear that cannot deliver the reference's acceleration at the current speed is
    # replaced by one that can: the truck stays close behind the reference (with only holding
    # speed asked of the state it fell 1.6-2.8 m/s behind, 0.14-0.23 m/s on average). Asked
    # for gear 10 from below, where it serves but not after the upshift, Level 0 steps up
    # through the gears between (`plant.protected_state`): open seconds more on the way, 1.24
    # m/s behind at most, 0.05 on average, a trip 0.6 s longer (before the steps 0.82 / 0.03)
    res = run_fixed_gear(jnp.asarray(gear))
    assert bool(res.final.done)
    live = np.asarray(res.trace.t) < float(res.final.tot.trip_time)
    short = (np.asarray(res.trace.v_ref) - np.asarray(res.trace.v))[live]
    assert short.max() < 1.4 and short.mean() < 0.1
    assert float(res.final.tot.trip_time) <= float(PRED.trip_time) * 1.03 + 1


def test_trip_time_close_to_level3():
    res = run(VP, -2.2)
    # the greedy controller switches often (each switch opens the driveline for 1 s)
    assert float(res.final.tot.trip_time) >= float(PRED.trip_time) - 1
    assert float(res.final.tot.trip_time) < 1.5 * float(PRED.trip_time)
    # ROUTE ends at a stop of 2 s, as Level 3's trip time counts it: the trip ends 2 s after
    # the truck comes to rest there, braking at constant deceleration within its last step
    # (2 ds / v0 into it), or at that step's end where the step, capped to end at the stop,
    # reaches it rolling (the conventional truck here; its speed then braked away). It
    # stands there: idling, for the conventional truck (`test_conventional_idles...`)
    for vp, res in ((VP, res), (VP.conventional(), run(VP.conventional(), -2.2))):
        t, s, v = (np.asarray(x) for x in (res.trace.t, res.trace.s, res.trace.v))
        k = int(np.flatnonzero(s < float(ROUTE.length) - 1e-3)[-1])  # the step that arrives
        assert s[k + 1] == pytest.approx(float(ROUTE.length)) and v[k + 1] == 0.0
        t_rest = t[k] + min(2.0 * (s[k + 1] - s[k]) / v[k], 1.0)
        assert float(res.final.tot.trip_time) == pytest.approx(t_rest + 2.0, abs=1e-9)
        assert rel_balance(res, vp) < BALANCE_RTOL
        # at a stop the truck stands: it never runs a step from a stop's position still
        # moving (reached rolling, it is braked to rest at the end of the step that reaches it)
        at_stop = np.isclose(s[:, None], [0.0, 800.0, float(ROUTE.length)], atol=1e-6).any(1)
        assert at_stop.sum() > 10 and np.all(v[at_stop] == 0.0)
        # standing there in the open mode: no launch state engaged in the stop's last second
        end = (t > t[k]) & (t < float(res.final.tot.trip_time))
        assert end.sum() >= 2 and np.all(np.asarray(res.trace.mode)[end] == ps.MO)


def test_open_driveline_during_switches():
    res = run(VP, -2.2)
    tr = res.trace
    mode = np.asarray(tr.mode)
    switched = np.flatnonzero(np.diff(mode) != 0) + 1
    assert switched.size > 0
    # a step in which the mode changed has no traction: no engine or motor power
    assert np.allclose(np.asarray(tr.P_e)[switched], 0.0)
    assert np.allclose(np.asarray(tr.P_m)[switched], 0.0)


def test_battery_limits_enforced_small_battery():
    vp = VP.replace(E_b_max=0.15e6)
    for lam in (-1.0, -4.5):  # cheap battery: drains; expensive battery: fills by recuperation
        res = run(vp, lam)
        E = np.asarray(res.trace.E_b)
        assert E.min() >= -1e-6 and E.max() <= 0.15e6 * (1 + 1e-9)
        assert rel_balance(res, vp) < BALANCE_RTOL


def test_conventional_idles_and_never_uses_the_motor():
    vp = VP.conventional()
    res = run(vp, -2.2)
    tr = res.trace
    assert np.allclose(np.asarray(tr.P_m), 0.0) and np.allclose(np.asarray(tr.P_b), 0.0)
    assert set(np.unique(np.asarray(tr.mode))) <= {ps.ME, ps.MO}
    v = np.asarray(tr.v)
    # the steps the run counts: at the final stop the last counts the stop's time beyond its
    # second (1.11 s where the trip ends at 164.11 s), and the next, though it starts before
    # the trip's end, counts nothing
    live = np.asarray(tr.counted)[:-1] > 0
    standing = (v[:-1] == 0) & (v[1:] == 0) & live
    assert standing.sum() >= 15
    idle = float(P.idle_fuel_power(vp))
    assert np.allclose(np.asarray(tr.P_f)[:-1][standing], idle)


def test_vmap_equals_loop():
    masses = np.array([15e3, 25e3, 38e3])
    lams = np.array([-1.8, -2.2, -2.9])
    vps = VP._replace(mass=masses)
    batched = jax.vmap(run, in_axes=(vehicle_axes(VP, ["mass"]), 0))(vps, lams)
    for b in range(3):
        one = run(VP.replace(mass=masses[b]), float(lams[b]))  # a float: run's compilation
        np.testing.assert_allclose(np.asarray(batched.final.tot.fuel[b]),
                                   np.asarray(one.final.tot.fuel), rtol=1e-10)
        np.testing.assert_allclose(np.asarray(batched.trace.E_b[b]), np.asarray(one.trace.E_b),
                                   rtol=1e-10, atol=1e-6)


def test_unfinished_route_is_reported():
    """A truck that accelerates at 0.02 m/s^2 cannot finish within the plant's steps: the run
    reports no trip time (NaN, null in JSON; it reported 0 s) and status unfinished, and its
    time series keeps every step it ran (it kept none: the steps before a trip time of 0)."""
    vp = VP.replace(a_max=0.02)
    res = run(vp, -2.2)
    assert not bool(res.final.done)
    assert float(res.final.tot.trip_time) == 0.0
    m = S._metrics(res, PRED, vp, -2.2, S.OK)
    assert np.isnan(float(m.trip_time_s)) and int(m.status) & S.UNFINISHED
    assert float(m.fuel_J) == float(res.final.tot.fuel) > 0  # over the steps it ran
    r = S.Result(route="route", strategy="conventional", fields=m._asdict(), trace=res.trace,
                 prediction=PRED, plant=res)
    assert len(r.trace_columns()["t_s"]) == N_PLANT
    assert r.as_dict()["trip_time_s"] != r.as_dict()["trip_time_s"]  # NaN
    finished = run(VP, -2.2)
    done = S._metrics(finished, PRED, VP, -2.2, S.OK)
    assert float(done.trip_time_s) > 0 and int(done.status) == S.OK
    # a prediction whose trip does not fit its steps (simulate_batch given too few: it ran,
    # marked ok, on a prediction cut short) says so
    T = PRED.v.shape[0]
    for trip, short in ((T * float(PRED.dt) - 1e-6, False), (T * float(PRED.dt), True)):
        m = S._metrics(finished, PRED._replace(trip_time=trip), VP, -2.2, S.OK)
        assert bool(int(m.status) & S.STEPS_SHORT) is short
    assert S.status_text(S.STEPS_SHORT) == "level3-steps-short"


@settings(max_examples=40, deadline=None)
@given(log_beta=st.floats(-12.0, -3.0), share=st.floats(-1.5, 1.0))
def test_terminal_power_inverts_eq7_in_float32_too(log_beta, share):
    """`_pb_of_pbi` inverts P_bi = P_b + beta P_b^2 (eq. 7) on its physical root down to the
    least loss coefficient the vehicle files accept (1e-12 / W), and in float32 to float32's
    rounding away from the root's vertex (where any rounding of P_bi moves the root); an
    internal power below its least value, -1 / (4 beta), gives the vertex, -1 / (2 beta), to
    the square root of float64's rounding: 1 + 4 beta P_bi rounds to a few ulp there, not 0
    (beta 1e-5, share -1.5: 1.05e-8 of the power; found by a random-seed run).
    share: P_bi in units of 1 / (4 beta), capped at 1 MW."""
    beta = 10.0**log_beta
    P_bi = min(share / (4.0 * beta), 1e6)
    P_b = float(P._pb_of_pbi(VP.replace(beta=beta), P_bi))
    if share < -1.0:
        assert P_b == pytest.approx(-0.5 / beta, rel=5e-8)
        return
    assert P_b + beta * P_b * P_b == pytest.approx(P_bi, rel=1e-9, abs=1e-9 / beta)
    assert P_b >= -0.5 / beta * (1 + 1e-12)  # the physical root, not the other
    assert float(R._pb_of_pbi(VP.replace(beta=beta), P_bi)) == pytest.approx(P_b, rel=1e-12)
    if share > -0.8:
        vp32 = jax.tree.map(lambda x: np.asarray(x, np.float32), VP.replace(beta=beta))
        got = P._pb_of_pbi(vp32, jnp.asarray(P_bi, jnp.float32))
        assert got.dtype == jnp.float32 and float(got) == pytest.approx(P_b, rel=1e-6)


@pytest.mark.parametrize("v", [0.0, 3.0, 15.0])
def test_sync_energy_counts_each_inertia_that_spins_up(v):
    w = float(VP.gear_ratio[5] * VP.r_d * v)
    I_e, I_m = float(VP.I_e), float(VP.I_m)
    e = lambda vp, a, b: float(P.sync_energy(vp, a, 5, b, 5, v))  # noqa: E731
    assert e(VP, ps.MO, ps.MC) == pytest.approx(0.5 * (I_e + I_m) * w * w)
    assert e(VP, ps.MC, ps.MO) == 0.0
    # per component (Appendix C): the engine stopping does not spin the motor up
    assert e(VP, ps.ME, ps.MM) == pytest.approx(0.5 * I_m * w * w)
    assert e(VP.conventional(), ps.MO, ps.MC) == pytest.approx(0.5 * I_e * w * w)
    # a downshift spins both up from gear 6 to gear 4 speeds
    w4 = float(VP.gear_ratio[3] * VP.r_d * v)
    assert float(P.sync_energy(VP, ps.MC, 5, ps.MC, 3, v)) == pytest.approx(
        0.5 * (I_e + I_m) * (w4 * w4 - w * w))


def test_path_sync_energy_matches_a_loop():
    # the plant's vectorised path against a loop over the reference's plain synchronisation
    rng = np.random.default_rng(3)
    T = 40
    mode = jnp.asarray(rng.integers(0, 4, T))
    gear = jnp.asarray(rng.integers(0, 12, T))
    v = jnp.asarray(rng.uniform(0.0, 25.0, T))
    got = np.asarray(P.path_sync_energy(VP, mode, gear, v))
    want = np.zeros(T)
    for k in range(1, T):
        m0, g0, m1, g1 = int(mode[k - 1]), int(gear[k - 1]), int(mode[k]), int(gear[k])
        if m1 != m0 or (g1 != g0 and m1 != ps.MO):
            want[k] = R.ref_sync_energy(VP, m0, g0, m1, g1, v[k]) / float(VP.eta_m)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-9)


@settings(max_examples=30)
@given(v0=st.floats(0.0, 30.0), F0=st.floats(-2e4, 8e4), P=st.floats(-3e5, 3e5))
def test_motion_short_of_the_target_balances_its_energy(v0, F0, P):
    # m (v1^2 - v0^2) / 2 + F0 ds = P t: over the whole step where the truck keeps moving,
    # up to its stop (t = 2 ds / v0) where it comes to rest within the step
    m, dt = float(VP.mass), 1.0
    v1, ds = (float(x) for x in P_motion(VP, v0, F0, P, dt))
    assert v1 >= 0.0 and 0.0 <= ds <= 0.5 * (v0 + v1) * dt + 1e-12
    t = dt if v1 > 0 else (2.0 * ds / v0 if v0 > 0 else 0.0)
    assert t <= dt + 1e-12
    assert 0.5 * m * (v1**2 - v0**2) + F0 * ds == pytest.approx(P * t, rel=1e-9,
                                                                   abs=1e-6 * (1 + abs(P)))


P_motion = xla.jit(P._motion_short)


def np_mean_grade(s, ds):
    """Mean gradient of ROUTE over [s, min(s + ds, L)] by summing the cells' overlaps (the
    gradient at s where that stretch is empty)."""
    g, L, h = np.asarray(ROUTE.grade), float(ROUTE.length), float(ROUTE.ds)
    s1 = min(s + ds, L)
    if s1 - s <= 1e-3:
        return g[min(int(np.floor(s / h)), g.size - 1)]
    rise = sum(g[i] * max(0.0, min(s1, (i + 1) * h) - max(s, i * h)) for i in range(g.size))
    return rise / (s1 - s)


@settings(max_examples=40)
@given(s=st.floats(0.0, 1200.0), ds=st.floats(0.0, 40.0))
def test_mean_grade_matches_the_cells_overlaps(s, ds):
    got = float(_mean_grade(_track(), jnp.asarray(s), jnp.asarray(ds)))
    assert got == pytest.approx(np_mean_grade(s, ds), abs=1e-9)


ref_position = xla.jit(P._ref_position)
_mean_grade = xla.jit(P._mean_grade)
_track = functools.cache(lambda: P.make_track(ROUTE, PRED))  # after the module fixture


@settings(max_examples=40)
@given(pos=st.lists(st.floats(0.0, 1200.0), min_size=1, max_size=8),
       stands=st.lists(st.integers(1, 60), max_size=3))
def test_ref_position_is_the_step_that_contains_the_position(pos, stands):
    """(j, frac) against NumPy's search on the step ends ref_s[1:]: the Level 3 step whose
    span holds s (the last of several steps that end at s, as where the reference stands),
    clipped to the grid; s within rounding (1e-6 m) short of a step's end is at its end
    (`plant.at_or_past`): one ulp short of each step end tried, too."""
    track = _track()
    ref_s = np.asarray(track.ref_s).copy()
    for k in stands:  # standing steps: runs of equal positions
        ref_s[k:k + 3] = ref_s[k]
    ref_s = np.maximum.accumulate(ref_s)
    tr = track._replace(ref_s=jnp.asarray(ref_s)).with_search_blocks()
    T = ref_s.size - 1
    ends = ref_s[[0, 1, 5, T // 2, T]]
    for x in [*pos, *ends, *np.nextafter(ends, -np.inf)]:
        j, frac = ref_position(tr, jnp.asarray(x))
        j_np = min(max(int(np.searchsorted(ref_s[1:], R.ref_at_or_past(x), side="right")), 0),
                   T - 1)
        assert int(j) == j_np, x
        d = ref_s[j_np + 1] - ref_s[j_np]
        f_np = min(max((x - ref_s[j_np]) / d, 0.0), 1.0) if d > 0 else 0.0
        assert float(frac) == pytest.approx(f_np, abs=1e-12)


def test_road_work_is_the_gradient_of_the_distance_covered():
    """Each step's road load takes the mean gradient over its distance: the plant's road work
    is the sum over its steps of F_0(v, mean gradient over [s_k, s_k+1]) (s_k+1 - s_k), whatever
    the phase of the steps against the gradient's changes. Steps that fall short of their
    target (switches) take the gradient over the target's distance: 0.012 % here. The gradient
    at each step's start was 0.09 % off here (2 % of the short track's road work)."""
    res = run(VP, -2.0)
    s = np.append(np.asarray(res.trace.s), float(res.final.s))
    v = np.asarray(res.trace.v)
    road = sum(R.road_load(VP, v[k], np_mean_grade(s[k], s[k + 1] - s[k])) * (s[k + 1] - s[k])
               for k in range(v.size) if s[k + 1] > s[k])
    assert float(res.final.tot.road) == pytest.approx(road, rel=3e-4)
    assert float(res.final.s) == pytest.approx(float(ROUTE.length))  # the whole route


def test_final_braking_starts_after_the_references_last_traction():
    P_d, mask, s = (np.asarray(x) for x in (PRED.P_d, PRED.mask, PRED.s))
    last = max(k for k in range(P_d.size) if mask[k] and P_d[k] > 0)
    want = s[last + 1] if mask[last + 1] else float(PRED.length)
    assert float(P.make_track(ROUTE, PRED).final_s) == pytest.approx(want, abs=1e-9)
    assert np.isinf(float(P.make_track(ROUTE, PRED, end_cap=False).final_s))
    # the route ends braking to a stop: the final braking is a stretch of it
    assert 0.0 < want < float(PRED.length)


@settings(max_examples=10)
@given(mass=st.floats(12e3, 40e3), lam=st.floats(-4.5, -1.2), soc0=st.floats(0.2, 0.8))
def test_final_braking_stores_no_more_than_the_trip_started_with(mass, lam, soc0):
    vp = VP.replace(mass=mass, soc0=soc0)
    capped, free = run(vp, lam), run(vp, lam, end_cap=False)
    final_s = float(P.make_track(ROUTE, PRED).final_s)
    E0 = soc0 * float(VP.E_b_max)
    s = np.asarray(capped.trace.s)
    E_c = np.append(np.asarray(capped.trace.E_b), float(capped.final.E_b))
    E_f = np.append(np.asarray(free.trace.E_b), float(free.final.E_b))
    before = np.append(s < final_s, False)
    # the same run up to the final braking (equal to the bit here; to rounding, as another
    # code generation gives it: XLA at -O0 moved 37 of 157 values by 1 ulp)
    np.testing.assert_allclose(E_c[before], E_f[before], rtol=1e-12, atol=0)
    # then no step ends above the start's energy or above where it began, whichever is higher
    after = np.flatnonzero(~before[:-1])
    assert after.size > 0
    assert np.all(E_c[after + 1] <= np.maximum(E0, E_c[after]) * (1 + 1e-12) + 1e-6)
    # below the start's energy it stores as without the cap (a switch's synchronisation may
    # draw on it meanwhile, in both runs alike)
    end_c, end_f = float(capped.final.E_b), float(free.final.E_b)
    assert min(end_f, E0) - 1e-3 <= end_c <= end_f + 1e-3
    # the service brakes take the rest, and the engine charges no more there either: no more
    # fuel; the balance closes
    assert float(capped.final.tot.fuel) <= float(free.final.tot.fuel)
    assert float(capped.final.tot.loss_brake) >= float(free.final.tot.loss_brake) - 1e-6
    assert rel_balance(capped, vp) < BALANCE_RTOL


def test_final_braking_cap_binds_on_the_reference_truck():
    # the greedy controller arrives below the start's energy and its final braking would end
    # above it: with the cap it ends exactly there
    capped, free = run(VP, -2.2), run(VP, -2.2, end_cap=False)
    E0 = float(VP.soc0 * VP.E_b_max)
    assert float(free.final.E_b) > E0 + 1e3
    assert float(capped.final.E_b) == pytest.approx(E0, abs=1.0)


@pytest.mark.parametrize("v", [0.0, 0.4, 3.0, 15.0, 27.0])
def test_all_ranges_equal_each_states_own(v):
    got = P.all_ranges(VP, v)
    n_g = VP.gear_ratio.shape[0]
    for s in range(ps.N_MODES * n_g):
        want = P.state_ranges(VP, s // n_g, s % n_g, v)
        for name, a, b in zip(want._fields, got, want, strict=True):
            assert float(a[s]) == float(b) or (np.isnan(float(a[s])) and np.isnan(float(b))), (
                s, name)


_protect_full = xla.jit(functools.partial(P.protected_state, dt=1.0))
_protect = P.protection(1.0)  # as the plant's step calls it
_protect_one = xla.jit(_protect)
_protect_vmap = xla.jit(jax.vmap(_protect, in_axes=(None, 0, None, None, None, None, 0, None,
                                                     None, None)))
_requested_serves = xla.jit(functools.partial(P.requested_serves, dt=1.0))


@xla.jit
def _serving(vp, E_b, P_need, v, v_after, pb_plan):
    """(ok_now, ok_after) (S,): every state serves at v, and also at v_after."""
    ok_now = P.capable(vp, P.all_ranges(vp, v), E_b, P_need, 1.0, pb_plan)
    return ok_now, ok_now & P.capable(vp, P.all_ranges(vp, v_after), E_b, P_need, 1.0, pb_plan)


_S = ps.N_MODES * VP.gear_ratio.shape[0]
# a plan's battery power holding the motor in the engine's states (`plant.deliverable`), or none
PB_PLAN = st.one_of(st.just(float("inf")), st.floats(-150e3, 150e3))


@settings(max_examples=60, deadline=None)
@given(v=st.floats(0.0, 30.0), dv=st.floats(0.0, 3.0), P_need=st.floats(-50e3, 400e3),
       E_frac=st.floats(0.0, 1.0), lam=st.floats(-4.5, -1.0),
       s_req=st.integers(0, _S - 1), s_cur=st.integers(0, _S - 1), at_rest=st.booleans(),
       pb_plan=PB_PLAN)
def test_protection_with_its_shortcut_is_the_full_one(v, dv, P_need, E_frac, lam, s_req, s_cur,
                                                      at_rest, pb_plan):
    """Level 0 decided from the requested state alone where it serves, and by every state
    where it does not, gives the state of the full evaluation: one configuration, and under
    vmap (a batch where some requests serve and some do not, or all do)."""
    args = (VP, E_frac * VP.E_b_max, P_need, v, max(v - dv, 0.1), lam, s_req, s_cur, at_rest,
            pb_plan)
    want = int(_protect_full(*args))
    known, s = _requested_serves(*args)
    # the check from the requested state alone is the one from every state's table
    ok_now, ok_after = _serving(VP, args[1], P_need, v, args[4], pb_plan)
    ok = bool(ok_now[s_req]) if s_req == s_cur else bool(ok_after[s_req])
    assert bool(known) == (ok or at_rest) and int(s) == s_req
    if known:
        assert want == s_req
    assert int(_protect_one(*args)) == want
    E = jnp.asarray([0.0, E_frac * VP.E_b_max, VP.E_b_max])
    reqs = jnp.asarray([s_req, s_cur, s_req], jnp.int32)
    got = _protect_vmap(VP, E, *args[2:6], reqs, *args[7:])
    for e, r, g in zip(E, reqs, np.asarray(got), strict=True):
        assert int(g) == int(_protect_full(VP, e, *args[2:6], r, *args[7:]))


def assert_protection_equals_its_loop(v, grade, extra, E_frac, lam, mass, s_req, s_cur,
                                     hybrid, pb_plan=float("inf")):
    """`plant.protected_state` equals `reference._protect` for a truck needing its road
    load's power at v on this grade plus `extra` (W), a switch costing the speed the road
    load takes in one open second, a plan's battery power pb_plan (W, inf: none); returns the
    state."""
    vp = truck(hybrid, mass=mass)
    F0 = float(pt.road_load(vp, v, grade))
    v_after = max(v - max(F0, 0.0) / mass, 0.1)
    P_need = max(F0, 0.0) * v + extra
    args = (vp, E_frac * float(vp.E_b_max), P_need, v, v_after, lam, s_req, s_cur, False,
            pb_plan)
    want = R._protect(R._veh(vp), vp, *args[1:9], 1.0, pb_plan)
    assert int(_protect_full(*args)) == want
    return want


@settings(max_examples=60, deadline=None)
@given(v=st.floats(0.0, 30.0), grade=st.floats(-0.3, 0.3),
       extra=st.floats(-50e3, 400e3),
       E_frac=st.floats(0.0, 1.0), lam=st.floats(-4.5, -1.0),
       mass=st.floats(12e3, 40e3),
       s_req=st.integers(0, _S - 1), s_cur=st.integers(0, _S - 1), hybrid=st.booleans(),
       pb_plan=PB_PLAN)
def test_protection_equals_its_loop(v, grade, extra, E_frac, lam, mass, s_req, s_cur, hybrid,
                                    pb_plan):
    """Level 0 (`plant.protected_state`) against the reference's loop over every state
    (`reference._protect`), on any gradient up to +-30 %, with and without a plan holding the
    battery."""
    assert_protection_equals_its_loop(v, grade, extra, E_frac, lam, mass, s_req, s_cur, hybrid,
                                      pb_plan)


def test_protection_steps_toward_a_request_only_its_switch_keeps_out():
    """On 7.5 % at 30 km/h (18.2 t, M_c in gear 7, 40 kW over the road load's power), gear 10
    serves but not after an upshift's open second, and gears 8 and 9 do: Level 0 takes gear 9,
    the nearest the request (held in gear 7, the plant climbed 800 m there and burnt 11 % more
    than the conventional truck). Gears 11 and 12 do not serve at that speed at all, a request
    that may serve a step later: it holds gear 7, as before (no hunting)."""
    G = VP.gear_ratio.shape[0]
    got = [assert_protection_equals_its_loop(8.33, 0.075, 40e3, 0.5, -2.48, 18173.3,
                                             ps.MC * G + g, ps.MC * G + 6, True)
           for g in (9, 10, 11)]
    assert got == [ps.MC * G + 8, ps.MC * G + 6, ps.MC * G + 6]


@settings(max_examples=60, deadline=None)
@given(v=st.floats(1.0, 2.68), grade=st.floats(0.2, 0.3),
       extra=st.floats(-30e3, 400e3),
       E_frac=st.floats(0.0, 1.0), mass=st.floats(12e3, 40e3), s_req=st.integers(0, _S - 1),
       hybrid=st.booleans(), combined=st.booleans())
def test_protection_in_a_crawl_up_a_steep_climb(v, grade, extra, E_frac, mass, s_req, hybrid,
                                                combined):
    """Gear 1 near its top speed on 20-30 %, where a switch's open second costs 2-2.9 m/s:
    often no state serves after a switch, and the current state must then stay where it
    delivers at least what any other could after the open second (a switch for power stalled
    the truck). Against the reference's loop; where it stays, it is by that rule."""
    s_cur = (ps.MC if hybrid and combined else ps.ME) * VP.gear_ratio.shape[0]
    got = assert_protection_equals_its_loop(v, grade, extra, E_frac, -2.2, mass, s_req, s_cur,
                                            hybrid)
    if got == s_cur and s_req != s_cur:
        vp = truck(hybrid, mass=mass)
        F0 = float(pt.road_load(vp, v, grade))
        give_after = P.deliverable(vp, P.all_ranges(vp, max(v - F0 / mass, 0.1)),
                                   E_frac * float(vp.E_b_max), 1.0)
        give_now = P.deliverable(vp, P.all_ranges(vp, v), E_frac * float(vp.E_b_max), 1.0)
        others = np.delete(np.asarray(give_after), s_cur)
        assert float(give_now[s_cur]) >= others.max() or float(give_now[s_cur]) >= F0 * v + extra


_block_search = {side: xla.jit(functools.partial(P.block_search, side=side))
                 for side in ("left", "right")}
_interp = xla.jit(P._interp)
_pt_interp = xla.jit(pt.interp)
_SIZES = (5, 64, 65, 300)  # below, at and above one block; several blocks


@settings(max_examples=40, deadline=None)
@given(n=st.sampled_from(_SIZES), data=st.data())
def test_block_search_is_searchsorted(n, data):
    """`block_search` gives numpy's searchsorted index on sorted arrays with runs of equal
    values, for values before, within (on the values themselves) and after the array; and
    `_interp`, and `powertrain.interp` (its search compares with every node) on all the values
    at once, give jnp.interp's values to the last bit, where two nodes coincide too.
    (Subnormal values are left out, as in every property test: tests/conftest.py.)"""
    ints = data.draw(st.lists(st.integers(0, 40), min_size=n, max_size=n))
    a = np.sort(np.asarray(ints, np.float64)) * 2.5
    y = np.asarray(data.draw(st.lists(st.floats(-5.0, 5.0), min_size=n, max_size=n)))
    xs = [*a[[0, n // 2, n - 1]], -1.0, a[-1] + 1.0,
          *data.draw(st.lists(st.floats(-2.0, 105.0), min_size=1, max_size=6))]
    tr = P.Track(*(None,) * 11)._replace(ref_s=jnp.asarray(a), grid_s=jnp.asarray(a))
    tr = tr.with_search_blocks()
    for x in xs:
        for side in ("left", "right"):
            got = int(_block_search[side](tr.grid_s, tr.grid_c, jnp.asarray(x)))
            assert got == int(np.searchsorted(a, x, side=side)), (x, side)
        got = _interp(jnp.asarray(x), tr.grid_s, tr.grid_c, jnp.asarray(y))
        want = jnp.interp(jnp.asarray(x), jnp.asarray(a), jnp.asarray(y))
        assert float(got) == float(want), x
    x2 = jnp.asarray(xs)[:, None] + jnp.asarray([0.0, 0.5])  # (n, 2): any shape of x
    np.testing.assert_array_equal(_pt_interp(x2, jnp.asarray(a), jnp.asarray(y)),
                                  jnp.interp(x2, jnp.asarray(a), jnp.asarray(y)))


def scripted(cmds, cstate, vp, obs):
    """A controller that sends the command its script holds for this step."""
    mode, gear, lam, P_b, up, level0 = (a[obs.k] for a in cmds)
    return cstate, P.Command(mode=mode, gear=gear, lam=lam, P_b=P_b, catch_up=up,
                             level0_plan=level0)


@xla.jit
def run_script(vp, cmds, track):
    return P.run_plant(vp, track, scripted, cmds, jnp.zeros(()), ps.MO, 0, N_PLANT)


def wild_commands(rng, mode, gear, every=0.125):
    """The script (mode, gear, lam, P_b, catch_up, level0_plan), each (N_PLANT,): the given
    states with a random state requested at one step in `every`, costates, a plan's battery
    power at three steps in ten (nan elsewhere: the optimal split), catching up at half the
    steps, and Level 0 counting the plan's power at three in four."""
    n_g = VP.gear_ratio.shape[0]
    wild = rng.random(N_PLANT) < every
    mode = np.where(wild, rng.integers(0, ps.N_MODES, N_PLANT), mode).astype(np.int32)
    gear = np.where(wild, rng.integers(0, n_g, N_PLANT), gear).astype(np.int32)
    lam = rng.uniform(-3.5, -1.5, N_PLANT)
    P_b = np.where(rng.random(N_PLANT) < 0.3, rng.uniform(-60e3, 60e3, N_PLANT), np.nan)
    up = rng.random(N_PLANT) < 0.5
    return mode, gear, lam, P_b, up, rng.random(N_PLANT) < 0.75


def assert_plant_equals_its_loop(vp, cmds, route, pred, min_steps, v_atol=5e-5):
    """The plant's track equals `reference.ref_track`'s, and its run under the script `cmds`
    equals `reference.ref_plant`'s, step by step and in its totals; returns the run. v_atol:
    how far the speeds may part (m/s), what follows from it is derived below."""
    track = P.make_track(route, pred)
    res = run_script(vp, tuple(jnp.asarray(a) for a in cmds), track)
    ref_track = R.ref_track(route, pred)
    for name in ("ref_s", "ref_v", "grid_s", "grade", "rise", "stop_s", "stop_t", "length",
                 "final_s"):
        np.testing.assert_allclose(np.asarray(getattr(track, name)), getattr(ref_track, name),
                                   rtol=1e-12, atol=1e-9, err_msg=name)
    dt = 1.0
    steps, tot, final = R.ref_plant(vp, ref_track, cmds, N_PLANT, dt, ps.MO, 0)
    tr = res.trace
    n = int(np.sum(np.asarray(tr.t) < float(res.final.tot.trip_time))) if res.final.done \
        else N_PLANT
    assert n > min_steps and bool(res.final.done) == final["done"]
    for name in ("mode", "gear"):
        np.testing.assert_array_equal(np.asarray(getattr(tr, name))[:n],
                                      [getattr(x, name) for x in steps[:n]], err_msg=name)
    got = {name: np.asarray(getattr(tr, name))[:n] for name in (
        "s", "v", "v_ref", "E_b", "P_d", "P_e", "P_m", "P_b", "P_f", "P_brake")}
    want = {name: np.array([getattr(x, name) for x in steps[:n]]) for name in got}
    # the loop's optimal split is a search on H, which is flat to rounding within about 0.01 W
    # of its minimum (its curvature is the battery's -lambda_b beta), but to about 0.15 W in a
    # crawl up 30 % at 27.5 t (P_m 0.14 W apart, P_d 0.18 W on 197 kW): speeds short of their
    # target (which the powers set: 0.5 W over m v) to v_atol (5e-5 m/s; 1.6e-6 seen). What
    # depends on the speed parts with it: positions by dt times the speeds' gaps summed,
    # beyond 1e-4 m; each step's powers beyond 0.5 W or 1e-6 of them by up to 3 m v_max / dt
    # per m/s of its speeds' gap at its start or end (the demand m v dv/dt) and 3 m g / dt
    # times the largest change of gradient per m of its positions' gap (a step across a crest
    # climbs that much more or less: 11.8 W for 1.6e-4 m at the top of 30 %), the 3 for the
    # fuel, 2-3 times the engine's power; the reference speed, the track's at the truck's
    # position, by the track's steepest dv/ds times the positions' gap (on the last metres to
    # a stop, 1 m/s a step: 1e-6 m/s for 3e-7 m); the battery's energy, which sums the
    # powers, to 5 J and the powers' slack summed
    np.testing.assert_allclose(got["v"], want["v"], rtol=1e-8, atol=v_atol, err_msg="v")
    dv = np.abs(got["v"] - want["v"])
    dv_step = np.maximum(dv, np.append(dv[1:], 0.0))  # at the step's start or end
    s_gap = np.abs(got["s"] - want["s"])
    assert np.all(s_gap <= 1e-4 + 1e-8 * want["s"] + dt * np.cumsum(dv_step)), "s"
    m = float(vp.mass)
    jump = float(np.max(np.abs(np.diff(ref_track.grade))))  # the largest change of gradient
    p_slack = (3.0 * m * max(float(np.max(want["v"])), 1.0) * dv_step  # the speeds' gap
               + 3.0 * m * float(vp.g) * jump * np.maximum(s_gap, np.append(s_gap[1:], 0.0))) / dt
    for name in ("P_d", "P_e", "P_m", "P_b", "P_f", "P_brake"):
        gap = np.abs(got[name] - want[name])
        assert np.all(gap <= 0.5 + 1e-6 * np.abs(want[name]) + p_slack), (
            name, int(np.argmax(gap - p_slack)), float(np.max(gap - p_slack)))
    ds, dvr = np.diff(ref_track.ref_s), np.abs(np.diff(ref_track.ref_v))
    slope = float(np.max(np.where(ds > 1e-6, dvr / np.maximum(ds, 1e-6), 0.0)))
    assert np.all(np.abs(got["v_ref"] - want["v_ref"])
                  <= 1e-6 + 1e-8 * want["v_ref"] + slope * s_gap), "v_ref"
    e_slack = dt * np.cumsum(p_slack)  # what the powers' slack sums to, to each step
    assert np.all(np.abs(got["E_b"] - want["E_b"]) <= 5.0 + 1e-8 * want["E_b"] + e_slack), "E_b"
    e_total = float(e_slack[-1])
    # the totals part by what the steps' checks allow where the speeds part: the energies by
    # the powers' slack summed, the largest shortfall by the speeds' and reference speeds'
    # gaps, the trip time by the positions' gap over V_CRAWL / 2 (the trip's last step comes
    # to rest from V_CRAWL at the latest)
    t = res.final.tot
    for name in ("fuel", "road", "loss_engine", "loss_slip", "loss_motor", "loss_battery",
                 "loss_brake", "loss_sync"):  # J
        assert float(getattr(t, name)) == pytest.approx(tot[name], rel=1e-8,
                                                        abs=5.0 + e_total), name
    assert float(t.max_shortfall) == pytest.approx(
        tot["max_shortfall"], abs=1e-6 + float(np.max(dv + slope * s_gap)))
    for name in ("mode_switches", "gear_switches"):
        assert float(getattr(t, name)) == tot[name], name
    assert float(t.trip_time) == pytest.approx(
        tot["trip_time"], rel=1e-9, abs=1e-6 + float(np.max(s_gap)) / (0.5 * V_CRAWL))
    assert float(res.final.E_b) == pytest.approx(final["E_b"], rel=1e-9, abs=5.0 + e_total)
    assert_trace_closes(vp, res)
    return res


def assert_trace_closes(vp, res):
    """The trace accounts for every joule of the totals: the fuel is its fuel power over the
    time each step counts (`Trace.counted`) plus the synchronisation energy drawn from fuel, and
    each step's battery energy follows from the last by its internal power over that time and
    the synchronisation energy drawn from the battery, within the battery's limits."""
    tr, t = res.trace, res.final.tot
    trace_checks.assert_trace_closes(float(vp.beta), float(vp.E_b_max), tr.P_f, tr.P_b,
                                     tr.counted, tr.E_sync_f, tr.E_sync_b, tr.E_b,
                                     float(res.final.E_b), float(t.fuel), fuel_abs=1e-3)
    sync = np.sum(np.asarray(tr.E_sync_b)) + np.sum(np.asarray(tr.E_sync_f))
    assert sync == pytest.approx(float(t.loss_sync), rel=1e-10, abs=1e-3)


@settings(max_examples=8, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), mass=st.floats(15e3, 40e3),
       battery=st.floats(0.2e6, 4e6), hybrid=st.booleans())
def test_plant_equals_its_loop(seed, mass, battery, hybrid):
    """The plant's track is the one built by loops (`reference.ref_track`), and its scan equals
    the plant written as a loop over its steps (`reference.ref_plant`) under a scripted
    controller: the greedy run's states, a random state requested at one step in eight (Level
    0 must refuse many), the optimal split at a costate or a plan's battery power with or
    without catching up on the battery; the route has two stops, a climb and a descent; a
    small battery reaches its limits."""
    rng = np.random.default_rng(seed)
    vp = truck(hybrid, mass=mass, E_b_max=battery)
    base = run(vp, -2.2).trace
    cmds = wild_commands(rng, np.asarray(base.mode), np.asarray(base.gear))
    assert_plant_equals_its_loop(vp, cmds, ROUTE, PRED, 100)


@settings(max_examples=6, deadline=None)
@example(seed=0, mass=36e3, battery=0.2e6, hybrid=False)  # the heaviest, without the motor
@example(seed=0, mass=28048.0, battery=1216442.0, hybrid=True)  # v_ref parts at a stop
@given(seed=st.integers(0, 2**31 - 1), mass=st.floats(15e3, 36e3),
       battery=st.floats(0.2e6, 4e6), hybrid=st.booleans())
def test_a_gear_it_cannot_shift_out_of_holds_its_top_speed(seed, mass, battery, hybrid):
    """A launch at the foot of a 30 % climb, the script asking for a gear higher every 8 s
    (and a random state at one step in eight): a gear switch's open second there costs about
    2.9 m/s, so the truck cannot shift up out of gear 1 and crawls up at gear 1's top speed
    (`plant.held_top_speed`), never stalling, where it ran past that speed, was switched
    up, stalled within the second and launched again. The plant equals its loop.
    Up to 36 t: the engine slipping its clutch at idle pulls 1200 N m x 16.46 x 5.466 / m =
    108 kN in gear 1, what 30 % asks of 37.8 t, so a heavier truck without the motor slows
    along the climb (37.85 t: 0.433 -> 0.400 m/s, found by a random-seed run)."""
    rng = np.random.default_rng(seed)
    vp = truck(hybrid, mass=mass, E_b_max=battery)
    drive = ps.MC if hybrid else ps.ME
    ask = np.minimum(np.arange(N_PLANT) // 8, VP.gear_ratio.shape[0] - 1)
    cmds = wild_commands(rng, np.full(N_PLANT, drive), ask)
    # where the battery empties on the climb (2 MJ of motor power take it up), the engine
    # alone falls short of the top speed, and the speed it loses costs it power at the lower
    # engine speed: a gap of rounding (9 mJ of E_b as it empties) grows 2-3 times a step
    # (7e-8 m/s to 1.2e-5 m/s in 7 steps) until a step at the held top speed closes it; 2.1e-4
    # m/s at most in 120 random hybrid draws (4 beyond 5e-5)
    res = assert_plant_equals_its_loop(vp, cmds, STEEP, PRED_STEEP, 40, v_atol=5e-4)
    tr = res.trace
    s, v, gear = (np.asarray(x) for x in (tr.s, tr.v, tr.gear))
    climb = (s > 5.0) & (s < 140.0)  # the launch is behind, the crest ahead
    # no stall on the climb (a heavy truck is still launching at 5 m: 0.4998 m/s at 37.5 t)
    assert climb.sum() > 20 and np.all(v[climb] > 0.4)
    v_top = float(min(vp.we_max, vp.wm_max) / (vp.gear_ratio[0] * vp.r_d))
    assert np.all(v[climb] <= v_top) and np.all(gear[climb] == 0)
    assert np.sum(np.abs(v[climb] - v_top) < 1e-3 * v_top) > 10  # held at the top


held_top = xla.jit(lambda vp, mode, gear, F0, E_b: P.held_top_speed(vp, mode, gear, F0, E_b,
                                                                    1.0))


@settings(max_examples=40)
@given(mode=st.integers(0, ps.N_MODES - 1), gear=st.integers(0, 11),
       grade=st.floats(-0.3, 0.3), v=st.floats(0.0, 30.0), E_b=st.floats(0.0, 4e6),
       mass=st.floats(12e3, 40e3), hybrid=st.booleans())
def test_held_top_speed_equals_its_loop(mode, gear, grade, v, E_b, mass, hybrid):
    """`plant.held_top_speed` against the reference's: the gear's top speed where the next
    gear cannot take over after a switch's open second, else +inf (open mode: always)."""
    vp = truck(hybrid, mass=mass)
    F0 = float(pt.road_load(vp, v, grade))
    got = float(held_top(vp, mode, gear, F0, E_b))
    want = R._held_top(R._veh(vp), mode, gear, F0, E_b, 1.0)
    assert got == pytest.approx(want, rel=1e-12) if np.isfinite(want) else np.isinf(got)
    if mode == ps.MO or (abs(grade) <= 0.01 and v <= 25.0 and gear < 11 and mode != ps.MM):
        assert np.isinf(got)  # open, or an engine mode on the flat: the next gear takes over


@pytest.mark.parametrize("mass, grade, mode, gear, hybrid, held", [
    (40e3, 0.15, ps.ME, 0, False, False),  # gear 2 runs after the open second, 2x the power
    (40e3, 0.17, ps.ME, 0, False, True),  # a shift there ran into a stall-and-launch loop
    (20e3, 0.30, ps.ME, 0, False, True),
    (20e3, 0.30, ps.MC, 0, True, True),
    (30e3, 0.04, ps.MM, 4, True, False),  # motor-only at its top: an engine mode takes over
    (40e3, 0.08, ps.MM, 0, True, False),
    (20e3, 0.0, ps.ME, 11, False, True),  # the top gear of a truck without a motor
])
def test_held_top_speed_only_where_no_faster_state_takes_over(mass, grade, mode, gear, hybrid,
                                                              held):
    """Where a heavy truck can still shift up on 15 %, or a hybrid at motor-only's top speed
    can go on with the engine, nothing holds it; on 17 % at 40 t or 30 % at 20 t gear 1 is
    held at its top speed, 2.68 m/s."""
    vp = truck(hybrid, mass=mass)
    v_top = float(P._top_speed(vp, mode, gear))
    got = float(held_top(vp, mode, gear, float(pt.road_load(vp, v_top, grade)), 0.5 * 4e6))
    assert (got == pytest.approx(v_top, rel=1e-4)) if held else np.isinf(got)


def test_engine_speed_nodes_interpolate_the_moving_steps_by_position():
    """The engine speed the iteration feeds back to Level 3 at each node of the route: the
    plan's speeds of the steps that move, interpolated by position (held beyond the first and
    the last; standing steps left out), by a loop over the nodes with numpy's interp."""
    T = PRED.v.shape[0]
    w = 100.0 + 50.0 * np.sin(np.arange(T) / 7.0)
    got = np.asarray(S._engine_speed_nodes(ROUTE, PRED, jnp.asarray(w)))
    m = np.asarray(PRED.mask) & (np.asarray(PRED.v) > 0)
    s, ws = np.asarray(PRED.s)[m], w[m]
    assert np.all(np.diff(s) > 0) and (~m & np.asarray(PRED.mask)).sum() >= 10  # stops
    want = [np.interp(x, s, ws) for x in np.asarray(PRED.profile.s)]
    np.testing.assert_allclose(got, want, rtol=1e-12)


repredict = xla.jit(lambda vp, pred, mode, w: S.repredict_level3(STEEP, vp, 1.0, 256, pred, mode,
                                                                 w))


@pytest.mark.parametrize("rpm", [600.0, 1600.0])
def test_fed_back_engine_speed_that_stalls_level3_keeps_the_prediction(rpm):
    """The iteration's omega fed back to Level 3 (`repredict_level3`) on the launch at the foot
    of a 30 % climb: with the engine at idle speed wherever it runs, Level 3 stalls on the climb
    and the prediction given is returned unchanged; at 1600 rpm it climbs, and the new
    prediction is Level 3's at those speeds (not the one given)."""
    T = PRED_STEEP.v.shape[0]
    mode = jnp.full(T, ps.MC, jnp.int32)
    w = jnp.full(T, rpm * np.pi / 30.0)
    fresh = S.level3(STEEP, VP, 1.0, 256, S._engine_speed_nodes(STEEP, PRED_STEEP, w))
    got = repredict(VP, PRED_STEEP, mode, w)
    assert bool(PRED_STEEP.feasible) and bool(fresh.feasible) == (rpm > 1000.0)
    want = fresh if fresh.feasible else PRED_STEEP
    for a, b in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(want)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12, atol=1e-12)
    assert np.max(np.abs(np.asarray(fresh.profile.v) - np.asarray(PRED_STEEP.profile.v))) > 0.1


def test_a_plan_holding_the_battery_downshifts_where_its_engine_falls_short():
    """A plan below its battery energy (catch_up False) holds the motor to its battery power
    in the engine's states, and Level 0 counts only that (`Command.level0_plan`): at 40 t on
    ROUTE's 5 % climb, a script asking M_c in a gear whose engine cannot hold the speed, with
    no battery power, gets a lower gear that can, and the battery gives at most the motor's
    drag at zero output (about 1 kW). Where Level 0 counts what the battery holds (the option
    off), it climbs in a higher gear and holds the speed on the battery: tens of kW."""
    vp = VP.replace(mass=40000.0)
    pred = predict_velocity(ROUTE, vp, n_steps=256)
    n, gear = N_PLANT, 10
    drawn, top = {}, {}
    for level0 in (True, False):
        cmds = (np.full(n, ps.MC, np.int32), np.full(n, gear, np.int32), np.full(n, -2.2),
                np.zeros(n), np.zeros(n, bool), np.full(n, level0))
        res = run_script(vp, tuple(jnp.asarray(a) for a in cmds), P.make_track(ROUTE, pred))
        tr = res.trace
        s, g = np.asarray(tr.s), np.asarray(tr.gear)
        climb = (s > 320.0) & (s < 480.0)
        assert bool(res.final.done) and rel_balance(res, vp) < BALANCE_RTOL
        drawn[level0] = float(np.max(np.asarray(tr.P_b)[climb]))
        top[level0] = int(np.max(g[climb]))
        if level0:
            assert np.all(g[climb] < gear)
            # at most the motor's drag in the step's gear at the run's top speed
            w = np.asarray(vp.gear_ratio)[g[climb]] * float(vp.r_d) * float(np.max(tr.v))
            drag = -np.asarray(pt.motor_friction(vp, w)) / float(vp.eta_m)
            assert np.all(np.asarray(tr.P_b)[climb] <= drag) and np.max(drag) < 1.5e3
    assert drawn[False] > 10e3 > 1.5e3 > drawn[True] and top[False] > top[True]


def test_commanded_motor_power_never_fights_the_service_brakes():
    """A plan's battery power is its own step's, not the plant's: commanded to drive the motor
    on every step (+80 kW), the plant still never drives it while the service brakes take
    power, and where it brakes in a motor-only state (not switching) the motor recuperates
    instead."""
    base = run(VP, -2.2).trace
    n = N_PLANT
    cmds = (np.asarray(base.mode), np.asarray(base.gear), np.full(n, -2.2), np.full(n, 80e3),
            np.ones(n, bool), np.ones(n, bool))
    res = run_script(VP, tuple(jnp.asarray(a) for a in cmds), P.make_track(ROUTE, PRED))
    tr = res.trace
    P_m, P_brake, P_d = (np.asarray(x) for x in (tr.P_m, tr.P_brake, tr.P_d))
    mode = np.asarray(tr.mode)
    driving = P_m > 1.0
    assert driving.sum() > 20  # the command holds where the demand takes it
    braking = P_brake < -1.0
    assert braking.sum() > 5
    assert not np.any(driving & braking)
    gear = np.asarray(tr.gear)
    held = np.r_[False, (mode[1:] == mode[:-1]) & (gear[1:] == gear[:-1])]  # not opened
    regen = (mode == ps.MM) & (P_d < -1.0) & held
    assert regen.sum() > 0 and np.all(P_m[regen] < 0.0)
    assert rel_balance(res, VP) < BALANCE_RTOL
