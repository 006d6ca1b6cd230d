"""Level 3 velocity prediction: NumPy references, paper numbers, properties, vmap == loop."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jaxems import xla
from jaxems.io import load_route
from jaxems.levels import velocity as vel
from jaxems.levels.velocity import (
    V_CRAWL,
    energy_summary,
    predict_batch,
    predict_velocity,
    velocity_profile,
)
from jaxems.params import KMH, RPM, load_vehicle
from jaxems.reference import ref_pieces, ref_profile, ref_time_grid
from jaxems.reference import road_load as np_road_load
from jaxems.route import Row, n_nodes, node_positions, pad_routes, route_from_rows

VP = load_vehicle()
VP25 = VP.replace(mass=25000.0)


def make(*data, ds=10.0, bucket=512):
    return route_from_rows([Row(*r, line=i + 2) for i, r in enumerate(data)], ds=ds, bucket=bucket)


# a route with a standing start, limit changes, steep climbs and descents, stops, standing end
MIXED = make(
    (0, 0, 0, 5),
    (10, 60, 0, 0),
    (400, 60, 8, 0),
    (900, 40, -9, 0),
    (1300, 0, 0, 20),
    (1310, 80, 3, 0),
    (2500, 30, 0, 0),
    (2700, 80, -4, 0),
    (3400, 0, 0, 7),
)


# ------------------------------------------------------------------------------ references
@pytest.mark.parametrize(
    "route_name,mass", [("short_track", 25000.0), ("RegionalDelivery", 20000.0)]
)
def test_profile_matches_numpy_loop_bundled(route_name, mass):
    route = load_route(route_name)
    vp = VP.replace(mass=mass)
    prof = vel._profile_jit(route, vp, vel._w_pred_array(vp, None, route.grade.shape[0]))
    n = n_nodes(route)
    v, vf, vb, ok = ref_profile(route, vp)
    np.testing.assert_allclose(np.asarray(prof.v)[:n], v, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(np.asarray(prof.v_fwd)[:n], vf, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(np.asarray(prof.v_bwd)[:n], vb, rtol=1e-10, atol=1e-10)
    assert bool(prof.feasible) == ok
    _, trip = ref_pieces(route, v)
    assert float(prof.trip_time) == pytest.approx(trip, rel=1e-10)


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), mass=st.floats(15e3, 40e3))
def test_profile_with_engine_speed_per_node_matches_numpy_loop(seed, mass):
    # from the second iteration on, Level 3 predicts with Level 1's engine speed per node
    # (`repredict_level3`): a varying speed against the loops
    vp = VP.replace(mass=mass)
    N, n = MIXED.grade.shape[0], n_nodes(MIXED)
    w = np.random.default_rng(seed).uniform(700.0, 1800.0, N) * RPM
    prof = vel._profile_jit(MIXED, vp, w)
    v, vf, vb, ok = ref_profile(MIXED, vp, w[:n])
    np.testing.assert_allclose(np.asarray(prof.v)[:n], v, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(np.asarray(prof.v_fwd)[:n], vf, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(np.asarray(prof.v_bwd)[:n], vb, rtol=1e-10, atol=1e-10)
    assert bool(prof.feasible) == ok


@pytest.mark.parametrize("mass,w_rpm", [(20000.0, 1100.0), (40000.0, 800.0)])
def test_time_grid_matches_numpy_reference(mass, w_rpm):
    vp = VP.replace(mass=mass, w_pred=w_rpm * RPM)
    pred = predict_velocity(MIXED, vp, dt=1.0)
    n = n_nodes(MIXED)
    v, _, _, ok = ref_profile(MIXED, vp)
    np.testing.assert_allclose(np.asarray(pred.profile.v)[:n], v, rtol=1e-10, atol=1e-10)
    assert bool(pred.feasible) == ok
    T = pred.t.shape[0]
    dist, P, v_at, trip = ref_time_grid(MIXED, vp, v, 1.0, T)
    assert float(pred.trip_time) == pytest.approx(trip, rel=1e-10)
    np.testing.assert_allclose(np.asarray(pred.v), dist / 1.0, atol=1e-8)
    np.testing.assert_allclose(np.asarray(pred.P_d), P, rtol=1e-8, atol=1e-3)
    m = np.asarray(pred.mask)
    np.testing.assert_allclose(np.asarray(pred.v_ref)[m], v_at[m], atol=1e-9)
    np.testing.assert_allclose(
        np.asarray(pred.s), np.concatenate([[0], np.cumsum(dist)[:-1]]), atol=1e-7
    )


def test_short_track_power_on_slopes_matches_paper():
    vp = VP25.replace(v_cruise=25 * KMH)
    pred = predict_velocity(load_route("short_track"), vp)
    m = np.asarray(pred.mask)
    g = np.round(np.asarray(pred.grade)[m] * 100, 6)
    P = np.asarray(pred.P_d)[m] / 1e3
    v = 25 * KMH
    for slope, paper in ((6, 113), (-12, -192), (12, 215), (-6, -90)):
        on = g == slope
        assert on.sum() >= 5
        road = np_road_load(vp, v, slope / 100) * v / 1e3  # pure road load at 25 km/h
        np.testing.assert_allclose(P[on], road, rtol=1e-9)
        assert abs(P[on].mean() - paper) <= 0.05 * abs(paper)
    assert np.allclose(np.asarray(pred.v)[m][:-1], v)  # cruises at 25 km/h from the start


# ------------------------------------------------------------------------------ properties
def _src_limit(rows):
    s = np.array([r.s_m for r in rows]) - rows[0].s_m
    v = np.array([r.v_kmh for r in rows]) * KMH
    eff = v.copy()
    for j in range(len(v)):
        k = j
        while eff[j] == 0 and k + 1 < len(v):
            k += 1
            eff[j] = v[k]
        if eff[j] == 0:
            eff[j] = eff[j - 1]
    return lambda x: eff[np.minimum(np.searchsorted(s, x, side="right") - 1, len(s) - 2)]


route_rows = st.lists(
    st.tuples(
        st.floats(20.0, 400.0),
        st.sampled_from([0.0, 15.0, 40.0, 60.0, 85.0, 100.0]),
        st.floats(-10.0, 10.0),
        st.floats(1.0, 30.0),
    ),
    min_size=2,
    max_size=7,
)


def _rows(spec):
    s = np.cumsum([0.0] + [d for d, *_ in spec[1:]])
    rows = [
        Row(float(s[k]), v, g, stop if v == 0 else 0.0, k + 2)
        for k, (_, v, g, stop) in enumerate(spec)
    ]
    if all(r.v_kmh == 0 for r in rows):
        rows[1] = rows[1]._replace(v_kmh=50.0, stop_s=0.0)
    return rows


@settings(max_examples=25)
@given(route_rows, st.floats(8000.0, 40000.0), st.sampled_from([0.5, 1.0, 2.0]))
def test_properties(spec, mass, dt):
    rows = _rows(spec)
    route = route_from_rows(rows, ds=10.0)
    vp = VP.replace(mass=mass)
    pred = predict_velocity(route, vp, dt=dt)
    prof = pred.profile
    n = n_nodes(route)
    m = np.asarray(pred.mask)
    v_n = np.asarray(prof.v)[:n]
    lim = np.asarray(prof.vlim)[:n]
    stop = np.asarray(route.stop)[:n]
    L = float(route.length)
    assert bool(pred.feasible)
    # v <= vmax everywhere: at the nodes, at every t_k, and the step means
    assert np.all(v_n <= lim + 1e-12) and np.all(v_n >= 0)
    limit = _src_limit(rows)
    s_k = np.asarray(pred.s)[m]
    vr = np.asarray(pred.v_ref)[m]
    assert np.all(
        vr <= np.minimum(limit(np.minimum(s_k, L * (1 - 1e-12))), float(vp.v_cruise)) + 1e-9
    )
    s_next = np.append(s_k[1:], L)
    x = node_positions(route)[:n]
    for sa, sb, vk in zip(s_k, s_next, np.asarray(pred.v)[m], strict=True):
        near = (x >= sa - float(route.ds)) & (x <= sb + float(route.ds))
        assert vk <= lim[near].max() + 1e-9
    # acceleration within the limits, on the grid and on the time steps
    acc = np.diff(v_n**2) / (2 * float(route.ds))
    assert np.all(acc <= float(vp.a_max) + 1e-9) and np.all(acc >= -float(vp.a_min) - 1e-9)
    a_k = np.asarray(pred.a)[m]
    assert np.all(a_k <= float(vp.a_max) + 1e-9) and np.all(a_k >= -float(vp.a_min) - 1e-9)
    # the driveline power never exceeds the engine's power at w_pred (forward pass by design)
    p_max = float(np.interp(vp.w_pred, vp.te_max_w, vp.te_max) * vp.w_pred)
    assert np.asarray(pred.P_d).max() <= p_max * (1 + 1e-9)
    # v = 0 at stops for their duration
    t_arr, t_dep = np.asarray(prof.t_arr)[:n], np.asarray(prof.t_dep)[:n]
    assert np.all(v_n[stop > 0] == 0)
    t_k = np.asarray(pred.t)
    for i in np.flatnonzero(stop > 0):
        assert t_dep[i] - t_arr[i] == pytest.approx(stop[i])
        inside = (t_k >= t_arr[i]) & (t_k <= t_dep[i]) & m
        assert np.all(np.asarray(pred.v_ref)[inside] == 0)
        assert np.allclose(np.asarray(pred.s)[inside], x[i])
        whole = (t_k >= t_arr[i]) & (t_k + dt <= t_dep[i])
        assert whole.sum() >= math.floor(stop[i] / dt) - 1
        assert np.all(np.asarray(pred.v)[whole] == 0) and np.all(np.asarray(pred.P_d)[whole] == 0)
    # the time grid covers the route: sum of v dt is the length, the mask the trip time
    assert np.sum(np.asarray(pred.v)[m]) * dt == pytest.approx(L, rel=1e-3)
    assert m.sum() == math.ceil(float(pred.trip_time) / dt - 1e-9)
    # energy: sum P_d dt = kinetic energy change + road-load work (fine quadrature in s)
    s_f = np.linspace(0, L, 40001)
    v2 = np.interp(s_f, x, v_n**2)
    g_f = np.asarray(route.grade)[np.minimum((s_f / float(route.ds)).astype(int), n - 2)]
    F = np_road_load(vp, np.sqrt(v2), g_f)
    work = np.sum(0.5 * (F[1:] + F[:-1]) * np.diff(s_f))
    dke = 0.5 * mass * (v_n[-1] ** 2 - v_n[0] ** 2)
    assert np.sum(np.asarray(pred.P_d)) * dt == pytest.approx(dke + work, rel=1e-3, abs=2e3)


def test_start_and_end():
    flying = make((0, 50, 0, 0), (500, 50, 0, 0))
    p = predict_velocity(flying, VP)
    assert float(p.v_ref[0]) == pytest.approx(50 * KMH)
    assert float(p.trip_time) == pytest.approx(500 / (50 * KMH))
    p = predict_velocity(MIXED, VP)
    assert float(p.v_ref[0]) == 0 and float(p.v[0]) < float(p.v[20])
    n = n_nodes(MIXED)
    assert float(p.profile.v[n - 1]) == 0.0
    assert float(p.profile.t_dep[n - 1] - p.profile.t_arr[n - 1]) == 7.0


def test_stall_is_flagged():
    steep = make((0, 40, 0, 0), (100, 40, 30, 0), (600, 40, 0, 0), (700, 40, 0, 0))
    heavy = VP.replace(mass=90000.0)  # F_grade > peak torque force in gear 1
    p = predict_velocity(steep, heavy)
    assert not bool(p.feasible)
    n = n_nodes(steep)
    assert np.all(np.asarray(p.profile.v)[:n] >= V_CRAWL - 1e-12)
    assert math.isfinite(float(p.trip_time))
    assert bool(predict_velocity(steep, VP).feasible)  # the 20 t truck climbs it


def test_w_pred_per_node():
    climb = make((0, 85, 0, 0), (200, 85, 6, 0), (2200, 85, 0, 0))
    N = climb.grade.shape[0]
    slow = predict_velocity(climb, VP, w_pred=700 * RPM)
    same = predict_velocity(climb, VP, w_pred=np.full(N, 700 * RPM))
    np.testing.assert_array_equal(np.asarray(slow.P_d), np.asarray(same.P_d))
    base = predict_velocity(climb, VP)
    assert float(slow.trip_time) > float(base.trip_time)  # less engine power at 700 rpm


def test_bad_arguments():
    with pytest.raises(ValueError, match="too small"):
        predict_velocity(MIXED, VP, n_steps=10)
    with pytest.raises(ValueError, match="dt must be"):
        predict_velocity(MIXED, VP, dt=0.0)
    with pytest.raises(ValueError, match="use predict_batch"):
        predict_velocity(pad_routes([MIXED, MIXED]), VP)
    with pytest.raises(ValueError, match="pair them"):
        predict_batch([MIXED, MIXED], [VP, VP, VP])


# ------------------------------------------------------------------------- batching, jit
ROUTES = [load_route("short_track"), MIXED, make((0, 70, 2, 0), (4000, 70, -2, 0))]


def _assert_member(batch, b, single):
    for name in ("t", "s", "v", "a", "grade", "P_d", "v_ref", "mask", "trip_time", "feasible"):
        np.testing.assert_allclose(
            np.asarray(getattr(batch, name))[b],
            np.asarray(getattr(single, name)),
            rtol=1e-12,
            atol=1e-9,
        )


def test_vmap_over_routes_and_vehicles_equals_loop():
    vps = [VP, VP.replace(mass=30000.0), VP.replace(mass=12000.0, v_cruise=60 * KMH)]
    batch = predict_batch(ROUTES, vps)
    T = batch.t.shape[1]
    padded = pad_routes(ROUTES)
    assert batch.P_d.shape == (3, T)
    for b, (r, v) in enumerate(zip(ROUTES, vps, strict=True)):
        # the same route unpadded (own bucket) and padded to the batch give the same result
        _assert_member(batch, b, predict_velocity(r, v, n_steps=T))
        rb = type(r)(*(np.asarray(x)[b] for x in padded))
        _assert_member(batch, b, predict_velocity(rb, v, n_steps=T))
    # one route, a batch of vehicles
    many = predict_batch(MIXED, vps)
    for b, v in enumerate(vps):
        _assert_member(many, b, predict_velocity(MIXED, v, n_steps=many.t.shape[1]))
    # engine speeds per member
    w = np.array([[700.0], [1100.0], [1500.0]]) * RPM
    per = predict_batch(MIXED, vps, w_pred=w)
    for b, v in enumerate(vps):
        one = predict_velocity(MIXED, v, n_steps=per.t.shape[1], w_pred=float(w[b, 0]))
        _assert_member(per, b, one)
    # a batch of routes, one vehicle
    routes_only = predict_batch(ROUTES, VP)
    for b, r in enumerate(ROUTES):
        _assert_member(routes_only, b, predict_velocity(r, VP, n_steps=routes_only.t.shape[1]))


def test_new_vehicle_values_do_not_recompile():
    traces = []

    def counted(route, vp, w):
        traces.append(1)
        return velocity_profile(route, vp, w)

    f = xla.jit(counted)
    N = MIXED.grade.shape[0]
    for mass, v0 in ((20000.0, 85 * KMH), (31000.0, 70 * KMH), (9000.0, 50 * KMH)):
        vp = VP.replace(mass=mass, v_cruise=v0)
        f(MIXED, vp, np.full(N, float(vp.w_pred)))
    route2 = make((0, 30, 1, 0), (3000, 50, -1, 0))  # another route of the same bucket
    f(route2, VP, np.full(N, float(VP.w_pred)))
    assert len(traces) == 1
    before = vel._profile_jit._cache_size()
    predict_velocity(MIXED, VP.replace(mass=27000.0))
    predict_velocity(MIXED, VP.replace(mass=28000.0))
    assert vel._profile_jit._cache_size() - before <= 1


def test_float32_agrees_with_float64():
    r32 = type(MIXED)(
        *(
            np.asarray(x, np.float32) if np.asarray(x).dtype == np.float64 else np.asarray(x)
            for x in MIXED
        )
    )
    v32 = type(VP)(*(np.asarray(x, np.float32) for x in VP))
    p32 = predict_velocity(r32, v32)
    p64 = predict_velocity(MIXED, VP)
    assert p32.P_d.dtype == np.float32
    e32, e64 = energy_summary(p32), energy_summary(p64)
    assert e32["trip_time_s"] == pytest.approx(e64["trip_time_s"], rel=1e-3)
    assert e32["energy_traction_MJ"] == pytest.approx(e64["energy_traction_MJ"], rel=1e-3)
    assert e32["energy_net_MJ"] == pytest.approx(e64["energy_net_MJ"], rel=1e-3, abs=1e-3)


@settings(max_examples=30)
@given(
    v=st.floats(0.0, 30.0),
    grade=st.floats(-0.08, 0.08),
    mass=st.floats(10e3, 40e3),
    dt_g=st.floats(0.0, 3.0),
)
def test_forward_acceleration_counts_the_upshifts(v, grade, mass, dt_g):
    """a_fwd is the full-traction acceleration slowed by the upshifts' open time: the plain
    formula without open time, never above it, and a step dv takes dv / a plus the shifts in it
    (k dv of open time, in which road load costs k dv F_0 / m of speed to make up at a)."""
    vp = VP.replace(mass=mass, dt_G=dt_g)
    w = float(vp.w_pred)
    a = float(vel.forward_acceleration(vp, v, grade, w))
    plain = float(vel.forward_acceleration(vp.replace(dt_G=0.0), v, grade, w))
    assert a <= plain + 1e-12
    if plain <= 0 or dt_g == 0:
        assert a == pytest.approx(plain, rel=1e-12, abs=1e-12)
        return
    # one upshift per speed ratio step above gear 1's top speed
    r = np.asarray(vp.gear_ratio)
    ln_r = math.log(float(r[0] / r[-1])) / (len(r) - 1)
    v1 = float(vp.we_max / (r[0] * vp.r_d))
    k = dt_g / (max(v, v1) * ln_r)
    assert float(vel.shift_time_per_speed(vp, v)) == pytest.approx(k, rel=1e-12)
    # time per unit speed: 1/a = 1/plain + k (1 + max(F_0 / (m plain), -1))
    f0 = float(np_road_load(vp, v, grade))
    time_per_speed = 1.0 / plain + k * (1.0 + max(f0 / (mass * plain), -1.0))
    assert a * time_per_speed == pytest.approx(1.0, rel=1e-9)


def test_open_time_lengthens_the_trip():
    fast = velocity_profile(MIXED, VP.replace(dt_G=0.0))  # launches from stops
    slow = velocity_profile(MIXED, VP)
    assert float(slow.trip_time) > float(fast.trip_time)
    assert np.all(np.asarray(slow.v) <= np.asarray(fast.v) + 1e-9)


def test_no_shift_time_without_ratio_steps():
    # gears of one ratio (a gearbox base of 1) need no upshifts: the plain acceleration, finite
    vp = VP.replace(gear_ratio=np.full(12, 7.0))
    k = np.asarray(vel.shift_time_per_speed(vp, np.array([0.0, 5.0, 20.0])))
    assert np.all(k == 0.0)
    a = float(vel.forward_acceleration(vp, 5.0, 0.0, float(vp.w_pred)))
    plain = float(vel.forward_acceleration(vp.replace(dt_G=0.0), 5.0, 0.0, float(vp.w_pred)))
    assert math.isfinite(a) and a == pytest.approx(plain, rel=1e-12)
