"""Guards B1..B5 (eqs. 37-41, derived again): equal Hamiltonians at each guard, and the
closed-form mode map against a brute-force minimisation over a fine P_b grid on both sides."""

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from jaxems import xla
from jaxems.levels import powersplit as ps
from jaxems.params import RPM, load_vehicle

BASE = load_vehicle()
GEAR = 5  # the gear whose speed we place at w


@xla.jit
def _split_and_guards(vp, P_d, v, lam):
    w = vp.gear_ratio[GEAR] * vp.r_d * v
    s = ps.mode_gear_split(vp, P_d, v, lam)
    return (
        s.H[:, GEAR],
        ps.guards(vp, w, lam),
        ps.interior_region(vp, P_d, w, lam),
        ps.closed_form_mode(vp, P_d, w, lam),
    )


def random_vehicle(eta_e, eta_m, beta, e0_lin, e0_quad, m0_lin, m0_quad):
    """Random efficiencies and frictions; limits far away (the guards' region)."""
    return BASE.replace(
        eta_e=eta_e,
        eta_m=eta_m,
        beta=beta,
        e0_lin=e0_lin,
        e0_quad=e0_quad,
        m0_lin=m0_lin,
        m0_quad=m0_quad,
        pm_max=1e9,
        tm_max=1e9,
        wm_max=1e5,
        te_max=np.asarray(BASE.te_max) * 1e3,
    )


vehicles = st.builds(
    random_vehicle,
    eta_e=st.floats(0.3, 0.5),
    eta_m=st.floats(0.8, 0.98),
    beta=st.floats(3e-7, 3e-6),
    e0_lin=st.floats(10.0, 60.0),
    e0_quad=st.floats(0.2, 1.2),
    m0_lin=st.floats(0.5, 10.0),
    m0_quad=st.floats(0.002, 0.05),
)
speeds_rpm = st.floats(700.0, 2200.0)


def speed_for(vp, rpm):
    return rpm * RPM / (float(vp.gear_ratio[GEAR]) * float(vp.r_d))


def brute_modes(vp, P_d, v, lam, n=400_001):
    """min over a fine P_b grid of H for M_c, M_e, M_m (limits inactive by construction)."""
    w = float(vp.gear_ratio[GEAR] * vp.r_d * v)
    eta, eta_m, beta = float(vp.eta_e), float(vp.eta_m), float(vp.beta)
    pe0 = -(float(vp.e0_lin) * w + float(vp.e0_quad) * w * w)
    pm0 = -(float(vp.m0_lin) * w + float(vp.m0_quad) * w * w)

    def H_of(P_b, engine, motor):
        P_m = np.where(motor, pm0 + np.where(P_b > 0, eta_m * P_b, P_b / eta_m), 0.0)
        x = P_d - P_m  # engine output (brakes take any negative remainder)
        fuel = np.maximum(x - pe0, 0.0) / eta if engine else 0.0
        H = fuel - lam * (P_b + beta * P_b * P_b)
        return np.where(engine | (x <= 1e-9 * abs(P_d) + 1e-9), H, np.inf)

    span = 4.0 * (abs(P_d) + 1.0 / (beta * abs(lam)) + 1e5)
    grid = np.linspace(-span, span, n)
    Hc = H_of(grid, True, True).min()
    He = float(H_of(np.zeros(1), True, False)[0])
    # motor-only: P_m >= P_d is required; the grid must contain the exact boundary point
    p_exact = (P_d - pm0) / eta_m if P_d > pm0 else (P_d - pm0) * eta_m
    Hm = min(H_of(grid, False, True).min(), float(H_of(np.array([p_exact]), False, True)[0]))
    return np.array([Hc, He, Hm])


@settings(max_examples=30)
@given(vp=vehicles, rpm=speeds_rpm, frac=st.floats(0.05, 0.95), which=st.sampled_from([1, 2]))
def test_lambda_guards_equal_hamiltonians(vp, rpm, frac, which):
    v = speed_for(vp, rpm)
    _, g, _, _ = _split_and_guards(vp, 1e5, v, -2.0)
    lam = float(g.B1 if which == 1 else g.B2)
    # any P_d in the region: the guard does not depend on P_d
    P_d = 5e3 + frac * 3e5
    H, _, interior, _ = _split_and_guards(vp, P_d, v, lam)
    assume(bool(interior))
    H = np.asarray(H)
    assert abs(H[ps.MC] - H[ps.ME]) <= 1e-9 * abs(H[ps.ME])


def _pd_guard_case(vp, rpm, frac, region):
    """(v, lam, guard P_d, the mode M_m is compared with) for a lambda inside `region`."""
    v = speed_for(vp, rpm)
    _, g, _, _ = _split_and_guards(vp, 1e5, v, -2.0)
    B1, B2 = float(g.B1), float(g.B2)
    if region == "B3":
        lam, other = B1 + frac * (0.7 * B1 - B1), ps.MC  # B1 < lam < 0.7 B1 < 0
    elif region == "B4":
        lam, other = B2 + frac * (B1 - B2), ps.ME
    else:
        lam, other = B2 - frac * 0.5, ps.MC
    _, g, _, _ = _split_and_guards(vp, 1e5, v, lam)
    return v, lam, float(getattr(g, region)), other


@settings(max_examples=30)
@given(
    vp=vehicles,
    rpm=speeds_rpm,
    frac=st.floats(0.05, 0.95),
    region=st.sampled_from(["B3", "B4", "B5"]),
)
def test_power_guards_equal_hamiltonians(vp, rpm, frac, region):
    v, lam, P_d, other = _pd_guard_case(vp, rpm, frac, region)
    assume(np.isfinite(P_d))
    H, _, interior, _ = _split_and_guards(vp, P_d, v, lam)
    assume(bool(interior))
    H = np.asarray(H)
    assert abs(H[ps.MM] - H[other]) <= 1e-9 * abs(H[other])


@settings(max_examples=20)
@given(
    vp=vehicles,
    rpm=speeds_rpm,
    frac=st.floats(0.05, 0.95),
    region=st.sampled_from(["B1", "B2", "B3", "B4", "B5"]),
    side=st.sampled_from([-1, 1]),
    pd_frac=st.floats(0.1, 0.9),
)
def test_closed_form_map_matches_brute_force(vp, rpm, frac, region, side, pd_frac):
    if region in ("B1", "B2"):
        v = speed_for(vp, rpm)
        _, g, _, _ = _split_and_guards(vp, 1e5, v, -2.0)
        lam0 = float(getattr(g, region))
        lam = lam0 + side * 2e-3 * abs(lam0)
        P_d = 5e3 + pd_frac * 3e5
    else:
        v, lam, P_d0, _ = _pd_guard_case(vp, rpm, frac, region)
        assume(np.isfinite(P_d0))
        P_d = P_d0 + side * (2e-3 * abs(P_d0) + 200.0)
    H, _, interior, mode = _split_and_guards(vp, P_d, v, lam)
    assume(bool(interior))
    brute = brute_modes(vp, P_d, v, lam)
    H = np.asarray(H)[:3]
    # the brute force is at least as high as the exact minimum and close to it
    assert np.all(brute >= H - 1e-6 * np.abs(H))
    assert np.allclose(brute, H, rtol=1e-7, atol=1.0)
    assert int(mode) == int(np.argmin(brute))


def test_reference_truck_guard_b1_near_paper():
    """DESIGN: the reference truck gives B1 near lambda_b = -1.98 (at 1200 rpm)."""
    g = ps.guards(BASE, 1200 * RPM, -2.0)
    assert float(g.B1) == pytest.approx(-1.98, abs=0.005)
    assert float(g.B2) < -1 / (float(BASE.eta_e) * float(BASE.eta_m)) < float(g.B1)


def test_guards_without_friction_collapse():
    """With P_m0 = 0, B1 = -eta_m/eta_e and B2 = -1/(eta_e eta_m) (Table 6 branch limits)."""
    vp = BASE.replace(m0_lin=0.0, m0_quad=0.0)
    g = ps.guards(vp, 1200 * RPM, -2.0)
    eta, eta_m = float(vp.eta_e), float(vp.eta_m)
    assert float(g.B1) == pytest.approx(-eta_m / eta, rel=1e-12)
    assert float(g.B2) == pytest.approx(-1 / (eta * eta_m), rel=1e-12)
