"""Switching costs of Appendix C: Table A1 (synchronisation), Table A2 (traction interruption),
the dense cost matrix against the NumPy reference (`jaxems.reference`), and the open-driveline
event against a time-stepped simulation."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jaxems import switching as sw
from jaxems import xla
from jaxems.levels import powersplit as ps
from jaxems.params import RPM, load_vehicle
from jaxems.reference import ref_cost_matrix

VP = load_vehicle()
PRM = sw.SwitchCostParams()
cost_matrix_j = xla.jit(sw.switch_cost_matrix)

PAPER_A1, PAPER_A1_AVG = sw.PAPER_A1, sw.PAPER_A1_AVG


def test_table_a1_matches_paper():
    t = sw.table_a1(VP, lam=-2.2)
    assert set(t) == set(sw.A1_TRANSITIONS)
    for name, paper in PAPER_A1.items():
        kJ = t[name][0] / 1e3
        if name == "G_down_Mc":
            # The paper prints 30 = 10 + 20 (its rounded M_m and M_e values); the inertias give
            # 1/2 (I_e + I_m) (w_1^2 - w_0^2) 2.2 = 31.2 kJ, the sum of the unrounded 10.4, 20.8.
            exact = 0.5 * 4.5 * ((1200 * RPM) ** 2 - (930 * RPM) ** 2) * 2.2 / 1e3
            assert kJ == pytest.approx(exact, rel=1e-12)
            assert kJ == pytest.approx(t["G_down_Mm"][0] / 1e3 + t["G_down_Me"][0] / 1e3)
            assert abs(kJ - paper) < 1.5
        else:
            assert abs(kJ - paper) < 1.0, (name, kJ, paper)
    for name, paper in PAPER_A1_AVG.items():
        assert abs(t[name][1] / 1e3 - paper) < 1.0, (name, t[name][1], paper)
        a, b = name.split("->")
        assert t[name][1] == pytest.approx(0.5 * (t[name][0] + t[f"{b}->{a}"][0]))


def test_table_a2_ordering_and_paper_values():
    vp = VP.replace(mass=25000.0)  # the paper's short-cycle truck
    rows = sw.table_a2(vp, slopes_pct=(0.0, 6.0, 12.0))
    cost = [r["cost_kJ"] for r in rows]
    dv = [r["speed_loss_mps"] for r in rows]
    dt = [r["time_loss_s"] for r in rows]
    assert cost[0] < cost[1] < cost[2]
    assert dv[0] < dv[1] < dv[2] and dt[0] < dt[1] < dt[2]
    assert not any(r["saturated"] for r in rows)
    # the paper's 6 % and 12 % rows (0.65 / 1.25 m/s, 0.07 / 0.22 s, 1.8 / 5.6 kJ) to within
    # what the different traction limit of our curves explains (see experiments/table_a2.py)
    assert dv[1] == pytest.approx(0.65, abs=0.03) and dv[2] == pytest.approx(1.25, abs=0.05)
    assert dt[1] == pytest.approx(0.07, abs=0.01) and dt[2] == pytest.approx(0.22, abs=0.03)
    assert cost[1] == pytest.approx(1.8, abs=0.25) and cost[2] == pytest.approx(5.6, abs=0.6)


def simulate_event(m, F0, v0, tau, F_max, dt=1e-5):
    """Time-stepped open-driveline event (Figure A1): coast tau s, then full traction until
    v_0 is recovered; returns (time loss, speed loss) with respect to cruising at v_0."""
    t, s, v = 0.0, 0.0, v0
    n = int(round(tau / dt))
    for _ in range(n):
        s += v * dt - 0.5 * F0 / m * dt * dt
        v -= F0 / m * dt
    v1 = v
    a = (F_max - F0) / m
    while v < v0:
        h = min(dt, (v0 - v) / a)
        s += v * h + 0.5 * a * h * h
        v += a * h
        t += h
    t_total = tau + t
    return t_total - s / v0, v0 - v1


@pytest.mark.parametrize("F0", [500.0, 8000.0, 20000.0])
def test_traction_loss_matches_simulation(F0):
    m, v0, tau, F_max = 20000.0, 7.0, 1.0, 30000.0
    vp = VP.replace(mass=m)
    r = sw.traction_loss(vp, F0, v0, tau, F_max, PRM)
    t_loss, v_loss = simulate_event(m, F0, v0, tau, F_max, dt=1e-4)
    assert float(r.speed_loss_mps) == pytest.approx(v_loss, rel=1e-6)
    assert float(r.time_loss_s) == pytest.approx(t_loss, rel=1e-3)
    assert float(r.cost) == pytest.approx(-PRM.lambda_t * t_loss, rel=1e-3)


def simulate_event_stopping(m, F0, v0, tau, F_max, dt=1e-3):
    """`simulate_event` where the truck may come to rest during the open driveline (uphill,
    v0 < F0 tau / m): it stays there (held, not rolling back) until traction returns, then
    recovers v0 at full traction; each step integrated exactly (constant acceleration)."""
    s, v, t = 0.0, v0, 0.0
    a0 = -F0 / m
    while t < tau - 1e-12:
        h = min(dt, tau - t)
        if v > 0 and v + a0 * h <= 0:  # at rest within the step
            h_stop = v / -a0
            s += 0.5 * v * h_stop
            v = 0.0
        elif v > 0:
            s += v * h + 0.5 * a0 * h * h
            v += a0 * h
        t += h
    v1, a, t_r = v, (F_max - F0) / m, 0.0
    while v < v0:
        h = min(dt, (v0 - v) / a)
        s += v * h + 0.5 * a * h * h
        v += a * h
        t_r += h
    return tau + t_r - s / v0, v0 - v1


@settings(max_examples=40, deadline=None)
@given(v0=st.floats(1.0, 10.0), tau=st.floats(0.2, 3.0), share=st.floats(0.02, 0.9))
def test_traction_loss_matches_simulation_also_where_the_truck_stops(v0, tau, share):
    """A20-A22 against the time-stepped event on climbs up to 0.9 of the largest traction
    force, open times of 0.2-3 s and speeds from v_min: also where the truck comes to rest
    while the driveline is open (the branch the fixed cases above never reached)."""
    m, F_max = 20000.0, 30000.0
    F0 = share * F_max
    r = sw.traction_loss(VP.replace(mass=m), F0, v0, tau, F_max, PRM)
    t_loss, v_loss = simulate_event_stopping(m, F0, v0, tau, F_max)
    assert float(r.speed_loss_mps) == pytest.approx(v_loss, rel=1e-9, abs=1e-9)
    assert float(r.time_loss_s) == pytest.approx(t_loss, rel=1e-6, abs=1e-9)
    assert float(r.cost) == pytest.approx(-PRM.lambda_t * t_loss, rel=1e-6, abs=1e-6)
    assert not bool(r.saturated)


def test_traction_loss_where_the_truck_stops_is_reached():
    """One event that ends at rest, fixed (the draws above reach such events, but which ones
    depends on Hypothesis): the whole speed lost, the time loss the simulation's."""
    m, F_max, v0, tau = 20000.0, 30000.0, 1.5, 3.0
    F0 = 0.5 * F_max  # 0.75 m/s^2: at rest after 2 s of the 3
    r = sw.traction_loss(VP.replace(mass=m), F0, v0, tau, F_max, PRM)
    assert float(r.speed_loss_mps) == v0
    t_loss, _ = simulate_event_stopping(m, F0, v0, tau, F_max)
    assert float(r.time_loss_s) == pytest.approx(t_loss, rel=1e-6)


def test_traction_saturated_and_downhill_use_kinetic_energy():
    m, v0 = 20000.0, 7.0
    vp = VP.replace(mass=m)
    up = sw.traction_loss(vp, 40000.0, v0, 1.0, 30000.0, PRM)  # F0 >= F_max: saturated
    v1 = v0 - 40000.0 / m
    assert bool(up.saturated)
    assert float(up.cost) == pytest.approx(-PRM.lambda_k * 0.5 * m * (v0**2 - v1**2))
    down = sw.traction_loss(vp, -10000.0, v0, 1.0, 30000.0, PRM)
    v1 = v0 + 10000.0 / m
    assert float(down.cost) == pytest.approx(-PRM.lambda_k * 0.5 * m * (v1**2 - v0**2))
    assert float(sw.traction_loss(vp, 0.0, v0, 1.0, 3e4, PRM).cost) == 0.0


@settings(max_examples=10)
@given(
    v=st.floats(0.5, 25.0),
    grade=st.floats(-0.12, 0.12),
    lam=st.floats(-3.0, -1.2),
    averaged=st.sampled_from([0.0, 0.5, 1.0]),
)
def test_cost_matrix_matches_reference(v, grade, lam, averaged):
    prm = sw.SwitchCostParams(averaged=averaged, lambda_t=-25e3, lambda_k=-2.2)
    C = np.asarray(cost_matrix_j(VP, v, grade, lam, prm))
    np.testing.assert_allclose(C, ref_cost_matrix(VP, v, grade, lam, prm), rtol=1e-10, atol=1e-6)
    assert np.all(C >= 0) and np.all(np.diag(C) == 0)
    # traction interruption is one event: a combined switch costs no more than the two steps
    n_g = VP.n_gears
    for m0, g0, m1, g1 in [(1, 4, 0, 6), (2, 9, 0, 3), (0, 5, 2, 8)]:
        s, mid, t = m0 * n_g + g0, m1 * n_g + g0, m1 * n_g + g1
        assert C[s, t] <= C[s, mid] + C[mid, t] + 1e-6


def test_eps_M_and_eps_G_are_slices():
    C = np.asarray(sw.switch_cost_matrix(VP, 10.0, 0.02, -2.0, PRM))
    eM = np.asarray(sw.eps_M(VP, 10.0, 0.02, -2.0, 4, PRM))
    eG = np.asarray(sw.eps_G(VP, 10.0, 0.02, -2.0, 1, PRM))
    n_g = VP.n_gears
    assert eM[1, 2] == C[1 * n_g + 4, 2 * n_g + 4]
    assert eG[3, 7] == C[n_g + 3, n_g + 7]
    # starting the engine costs more than starting the motor (inertia 3 vs 1.5 kg m^2)
    assert eM[ps.MM, ps.ME] > eM[ps.ME, ps.MM] > 0


def test_checked_params_make_array_leaves_that_share_one_compilation():
    """Python floats and NumPy scalars of any type give the same leaves: a new value (or the
    same value typed differently) does not recompile a jitted function of the parameters."""
    f = xla.jit(lambda p: p.lambda_t * p.lambda_k + p.averaged + p.weight * p.v_min)
    given_as = [
        None,
        sw.SwitchCostParams(lambda_t=-30e3, weight=np.float32(0.5)),
        sw.SwitchCostParams(lambda_k=np.float64(-2.0), averaged=np.int64(1), v_min=2),
    ]
    for p in given_as:
        q = sw.checked_params(p, np.float64)
        assert all(np.asarray(x).dtype == np.float64 and np.ndim(x) == 0 for x in q)
        raw = PRM if p is None else p
        assert [float(x) for x in q] == [float(x) for x in raw]
        expected = (float(raw.lambda_t) * float(raw.lambda_k) + float(raw.averaged)
                    + float(raw.weight) * float(raw.v_min))
        assert float(f(q)) == pytest.approx(expected, rel=1e-15)
    assert f._cache_size() == 1
    assert np.asarray(sw.checked_params(None, np.float32).lambda_t).dtype == np.float32


@pytest.mark.parametrize("field, value", [
    ("lambda_t", 1.0), ("lambda_k", 0.5), ("averaged", 1.5), ("averaged", -0.1),
    ("weight", -1.0), ("v_min", 0.0), ("lambda_t", float("nan")), ("v_min", np.ones(2)),
    ("weight", "1"), ("weight", 1j), ("weight", True),
])
def test_checked_params_name_the_bad_field(field, value):
    with pytest.raises(ValueError, match=f"switching.{field}: must be"):
        sw.checked_params(PRM._replace(**{field: value}), np.float64)
    with pytest.raises(ValueError, match="SwitchCostParams expected"):
        sw.checked_params({"lambda_t": -1.0}, np.float64)


def test_simulate_rejects_bad_switching_costs_before_compiling():
    import jaxems

    with pytest.raises(ValueError, match="switching.weight"):
        jaxems.simulate("short_track", strategy="conventional",
                        switching=PRM._replace(weight=-1.0))
