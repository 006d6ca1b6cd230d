"""Level 1: explicit minimisation of the Hamiltonian over every mode and gear (section 4).

    H_1 = P_f - lambda_b * P_bi                                               (eq. 35)

For one time step (P_d, v) and costate lambda_b, `mode_gear_split` minimises H_1 over the
battery power P_b for every mode M in (combined, engine-only, motor-only, open) and every gear
G, evaluated with `vmap` over the (M, G) grid. Infeasible (M, G) get H = +inf.

One generic kernel serves all four modes. With the engine connected (flag ce) and/or the motor
connected (flag cm), the powers at the split point satisfy

    P_e_out + P_m + P_brake = P_d,     P_brake <= 0 (service brakes dissipate only)

with P_m in [-P_m_lim, P_m_lim] (zero when the motor is open) and the engine output in
[P_e_min, P_e_max] (zero when open). Given P_m, the cheapest engine output is
max(P_d - P_m, P_e_min): brakes only take what the engine cannot absorb. As a function of P_b,
the fuel power is convex (a convex non-increasing function of P_m, itself concave in P_b) and
-lambda_b P_bi is convex for lambda_b < 0, so H is convex and piecewise smooth in P_b. Its
minimum over the feasible interval is therefore among a handful of candidates: the interval's
ends, the stationary points of the two smooth branches (Table 6, with the slipping-clutch factor
k below; k = 1 gives the paper's expressions)

    P_b* = -(lambda_b + k eta_m / eta_e) / (2 beta lambda_b)        if P_b > 0
    P_b* = -(lambda_b + k / (eta_e eta_m)) / (2 beta lambda_b)      if P_b <= 0

the kinks (P_b = 0; the engine at its friction power, where fuel starts; the engine at its brake
limit, where the service brakes start) and the vertex of the battery loss parabola
P_b = -1/(2 beta). For lambda_b >= 0 the branches are concave and the minimum is at an end or a
kink, also among the candidates, so the candidate search is exact for every lambda_b. The
stationary points are clipped to the interval (the clamping to component limits).

Speed feasibility: a connected engine needs w in [we_min, we_max], a connected motor w <= wm_max.
Launch: in gear 1 only, below idle speed the engine may run at we_min with a slipping clutch
(torque is passed, the speed difference is lost): engine power = k * output with k = we_min / w.
This lets the conventional truck launch; the hybrid launches on the motor.

Mode indices: 0 = combined M_c, 1 = engine-only M_e, 2 = motor-only M_m, 3 = open M_o.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from .. import powertrain as pt
from ..params import VehicleParams

MODES = ("combined", "engine", "motor", "open")
MODE_SHORT = ("Mc", "Me", "Mm", "Mo")
MC, ME, MM, MO = 0, 1, 2, 3
N_MODES = 4
# (engine connected, motor connected) per mode
ENGINE_CONNECTED = (True, True, False, False)
MOTOR_CONNECTED = (True, False, True, False)
# the modes without a battery-power choice for lambda_b <= 0: the demand fixes their split (M_e:
# no motor, M_m: no engine, and the motor's least power; M_o: neither), the same at every such
# lambda_b; only M_c's depends on it (`fixed_split`; tested)
FIXED_MODES = (ME, MM, MO)


class Split(NamedTuple):
    """The optimal power split of one (or every) mode and gear; shapes (4, n_gears) per step.

    H: Hamiltonian (W), +inf where infeasible; P_b: battery terminal power (W); P_e: engine
    crank power (W); P_m: motor mechanical power (W); P_f: fuel power (W); P_brake: service-brake
    power (W, <= 0); w: gearbox input speed (rad/s); feasible: bool.
    """

    H: jax.Array
    P_b: jax.Array
    P_e: jax.Array
    P_m: jax.Array
    P_f: jax.Array
    P_brake: jax.Array
    w: jax.Array
    feasible: jax.Array


def _safe_div(a, b):
    return a / jnp.where(b == 0, 1.0, b)


def idle_fuel_power(vp: VehicleParams):
    """Fuel power (W) of an engine idling at its lowest speed, declutched (conventional truck)."""
    return -pt.engine_friction(vp, vp.we_min) / vp.eta_e


class Ranges(NamedTuple):
    """What one (mode, gear) can do at gearbox speed w (scalars): engine output range
    [e_lo, e_hi] at the clutch, slip factor k and crank speed we (launch), engine friction pe0,
    motor limit m_lim and friction pm0 (zero when open), connection flags ce, cm, and ok: the
    state can run at this speed (and has the components it needs)."""

    e_lo: jax.Array
    e_hi: jax.Array
    k: jax.Array
    pe0: jax.Array
    we: jax.Array
    m_lim: jax.Array
    pm0: jax.Array
    ce: jax.Array
    cm: jax.Array
    ok: jax.Array


def component_ranges(vp: VehicleParams, w, ce, cm, launch) -> Ranges:
    """`Ranges` of a mode (ce, cm: engine / motor connected) at gearbox speed w (rad/s);
    launch: gear 1, whose clutch may slip below idle speed."""
    ce = jnp.asarray(ce)
    needs_motor = jnp.asarray(cm)
    cm = needs_motor & (vp.has_motor > 0.5)  # a conventional truck has no motor modes
    # engine: speed, slip factor k, output range [e_lo, e_hi] and friction at the crank
    slip = launch & (w < vp.we_min)
    we = jnp.where(slip, vp.we_min, w)
    k = jnp.where(slip, _safe_div(vp.we_min, w), 1.0)
    pe_min, pe_max = pt.engine_power_limits(vp, we)
    e_ok = (we >= vp.we_min * (1 - 1e-9)) & (we <= vp.we_max) & (w > 0)
    ok = jnp.where(ce, e_ok, True) & jnp.where(cm, w <= vp.wm_max, True) & (cm | ~needs_motor)
    return Ranges(
        # a slipping clutch passes torque from the faster engine to the wheels only: no braking
        e_lo=jnp.where(ce, jnp.where(slip, 0.0, _safe_div(pe_min, k)), 0.0),
        e_hi=jnp.where(ce, _safe_div(pe_max, k), 0.0),
        k=k, pe0=jnp.where(ce, pt.engine_friction(vp, we), 0.0), we=we,
        m_lim=jnp.where(cm, pt.motor_power_limit(vp, w), 0.0),
        pm0=jnp.where(cm, pt.motor_friction(vp, w), 0.0), ce=ce, cm=cm, ok=ok,
    )


def pb_of_pm(vp: VehicleParams, r: Ranges, P_m):
    """Battery power for motor output P_m (inverse of eq. 4); zero when the motor is open."""
    d = P_m - r.pm0
    return jnp.where(r.cm, jnp.where(d > 0, d / vp.eta_m, d * vp.eta_m), 0.0)


def pb_engine_lowest(vp: VehicleParams, r: Ranges, P_d):
    """Battery power whose motor output, with the engine at the lowest of its range (its drag;
    0 when open), meets the demand P_d, within the motor's range: the most the motor may
    deliver without the service brakes taking any of it."""
    return pb_of_pm(vp, r, jnp.clip(P_d - r.e_lo, -r.m_lim, r.m_lim))


def pb_engine_highest(vp: VehicleParams, r: Ranges, P_d):
    """Battery power whose motor output, with the engine at the top of its range, meets the
    demand P_d, no lower than the motor's limit allows: the most the motor may charge while
    the engine and it still deliver P_d (the lower end of `pb_engine_lowest`'s range)."""
    return pb_of_pm(vp, r, jnp.maximum(-r.m_lim, P_d - r.e_hi))


def pm_of_pb(vp: VehicleParams, r: Ranges, P_b):
    """Motor output for battery power P_b (eq. 4); zero when the motor is open."""
    return jnp.where(r.cm, r.pm0 + jnp.where(P_b > 0, vp.eta_m * P_b, P_b / vp.eta_m), 0.0)


class Setup(NamedTuple):
    """What one mode's minimisation over P_b needs that does not depend on lambda_b: its
    `Ranges` r, the feasible P_b interval [lo, hi], feasible, the fuel power of a declutched
    idling engine (idle), and the candidates that do not depend on lambda_b (`fixed`: the
    interval's ends, P_b = 0, the fuel kink, the brake kink and the loss parabola's vertex,
    clipped to the interval, in `candidates` order). Scalars (per mode and step)."""

    r: Ranges
    lo: jax.Array
    hi: jax.Array
    feasible: jax.Array
    idle: jax.Array
    fixed: tuple


def mode_setup(vp: VehicleParams, P_d, w, ce, cm, launch) -> Setup:
    """The lambda-free part of `_split_one` for one mode (ce, cm flags) at gearbox speed w."""
    dtype = jnp.result_type(P_d, w, float)
    r = component_ranges(vp, w, ce, cm, launch)
    pm_lo = jnp.maximum(-r.m_lim, P_d - r.e_hi)
    pm_hi = r.m_lim
    feasible = (pm_lo <= pm_hi) & r.ok
    pm_lo = jnp.minimum(pm_lo, pm_hi)
    lo, hi = pb_of_pm(vp, r, pm_lo), pb_of_pm(vp, r, pm_hi)
    kink_fuel = pb_of_pm(vp, r, P_d - _safe_div(r.pe0, r.k))
    kink_brake = pb_engine_lowest(vp, r, P_d)
    vertex = jnp.full_like(lo, -0.5 / vp.beta)
    # a conventional truck (no motor) idles its engine with the clutch open: idle fuel
    idle = jnp.where(~r.ce & (vp.has_motor < 0.5), idle_fuel_power(vp), 0.0)
    fixed = tuple(jnp.clip(c.astype(dtype), lo, hi)
                  for c in (lo, hi, jnp.zeros_like(lo), kink_fuel, kink_brake, vertex))
    return Setup(r, lo, hi, feasible, idle, fixed)


def stationary(vp: VehicleParams, s: Setup, lam):
    """The stationary points of H's discharging and charging branches (Table 6), clipped to
    the mode's interval: the candidates that depend on lambda_b."""
    two_bl = 2.0 * vp.beta * lam
    k, dtype = s.r.k, jnp.result_type(s.lo, lam, float)
    return tuple(jnp.clip(c.astype(dtype), s.lo, s.hi)
                 for c in (-_safe_div(lam + k * vp.eta_m / vp.eta_e, two_bl),
                           -_safe_div(lam + k / (vp.eta_e * vp.eta_m), two_bl)))


def candidates(fixed, stat):
    """Every candidate in the order the minimisation takes them (the first wins ties)."""
    return tuple(fixed[:3]) + tuple(stat) + tuple(fixed[3:])


def mode_powers(vp: VehicleParams, s: Setup, P_d, c):
    """(P_b, P_m, P_out, P_f) of candidate battery power c (in the interval: `Setup.fixed`,
    `stationary`)."""
    r = s.r
    P_m = pm_of_pb(vp, r, c)
    P_out = jnp.where(r.ce, jnp.clip(P_d - P_m, r.e_lo, r.e_hi), 0.0)
    P_f = jnp.where(r.ce, jnp.maximum(r.k * P_out - r.pe0, 0.0) / vp.eta_e, s.idle)
    return c, P_m, P_out, P_f


def running_min(cands, key: int = -1):
    """The candidate tuple with the least entry `key` (H), the first on ties; a running
    minimum, unrolled: one fused element-wise kernel (stacking them for an argmin was 10x
    slower under vmap)."""
    best = cands[0]
    for cand in cands[1:]:
        better = cand[key] < best[key]
        best = tuple(jnp.where(better, x, y) for x, y in zip(cand, best, strict=True))
    return best


def _split_one(vp: VehicleParams, P_d, w, lam, ce, cm, launch):
    """Minimise H over P_b for one mode (ce, cm flags) at gearbox speed w. Scalars in and out."""
    dtype = jnp.result_type(P_d, w, lam, float)
    s = mode_setup(vp, P_d, w, ce, cm, launch)

    def evaluate(c):  # (P_b, P_m, P_out, P_f, H) of candidate battery power c
        c, P_m, P_out, P_f = mode_powers(vp, s, P_d, c.astype(dtype))
        return c, P_m, P_out, P_f, P_f - lam * pt.battery_internal(vp, c)

    best = running_min([evaluate(c) for c in candidates(s.fixed, stationary(vp, s, lam))])
    P_b, P_m, P_out, P_f, H_c = best
    feasible = s.feasible
    H = jnp.where(feasible, H_c, jnp.inf)
    P_brake = jnp.minimum(P_d - P_out - P_m, 0.0)
    z = jnp.zeros_like(H)
    pick = lambda x: jnp.where(feasible, x, z)  # noqa: E731
    return Split(
        H=H,
        P_b=pick(P_b),
        P_e=pick(s.r.k * P_out),
        P_m=pick(P_m),
        P_f=pick(P_f),
        P_brake=pick(P_brake),
        w=w,
        feasible=feasible,
    )


def split_state(vp: VehicleParams, P_d, v, lam, mode, gear) -> Split:
    """The optimal split of one (mode, gear) (indices, may be traced): scalar `Split`."""
    w = pt.shaft_speeds(vp, v)[gear]
    return _split_one(vp, P_d, w, lam, jnp.asarray(ENGINE_CONNECTED)[mode],
                      jnp.asarray(MOTOR_CONNECTED)[mode], gear == 0)


def mode_gear_split(vp: VehicleParams, P_d, v, lam, modes: tuple | None = None) -> Split:
    """The optimal split of every (mode, gear) at one time step: `Split` of shape (4, n_gears).

    P_d: driveline power demand (W), v: vehicle speed (m/s), lam: battery costate lambda_b (-),
    all scalars; modes (static): the mode indices to split, in that order (Split of shape
    (len(modes), n_gears)), None: all four. `vmap` over the (M, G) grid; map over time with
    `jax.vmap` at the edge.
    """
    w = pt.shaft_speeds(vp, v)  # (G,)
    n_g = w.shape[-1]
    modes = tuple(range(N_MODES)) if modes is None else tuple(modes)
    ce = jnp.array([ENGINE_CONNECTED[m] for m in modes])
    cm = jnp.array([MOTOR_CONNECTED[m] for m in modes])
    launch = jnp.arange(n_g) == 0  # gear 1 may slip its clutch below idle speed
    per_gear = jax.vmap(_split_one, in_axes=(None, None, 0, None, None, None, 0))
    per_mode = jax.vmap(per_gear, in_axes=(None, None, None, None, 0, 0, None))
    return per_mode(vp, P_d, w, lam, ce, cm, launch)


def hamiltonian_table(vp: VehicleParams, P_d, v, lam) -> Split:
    """`mode_gear_split` over a time grid: P_d, v: (T,), lam: () or (T,) -> Split of (T, 4, G)."""
    lam = jnp.broadcast_to(lam, jnp.shape(P_d))
    return jax.vmap(mode_gear_split, in_axes=(None, 0, 0, 0))(vp, P_d, v, lam)


class FixedSplit(NamedTuple):
    """The split of `FIXED_MODES` at one step or over a time grid, which does not depend on
    lambda_b <= 0: P_f (W) fuel power, P_b (W) battery power, P_bi (W) the battery's internal
    power (`powertrain.battery_internal` of P_b), feasible; each (..., 3, G)."""

    P_f: jax.Array
    P_b: jax.Array
    P_bi: jax.Array
    feasible: jax.Array


def fixed_split(vp: VehicleParams, P_d, v) -> FixedSplit:
    """`FixedSplit` over a time grid (P_d, v: (T,)): once for every lambda_b <= 0."""
    def one(P_d, v):
        sp = mode_gear_split(vp, P_d, v, -1.0, FIXED_MODES)
        return FixedSplit(P_f=sp.P_f, P_b=sp.P_b, P_bi=pt.battery_internal(vp, sp.P_b),
                          feasible=sp.feasible)

    return jax.vmap(one)(P_d, v)


def hamiltonian_H(vp: VehicleParams, P_d, v, lam, fixed: FixedSplit | None = None):
    """(T, 4, G) W: `hamiltonian_table`'s H alone. With ``fixed`` (`fixed_split` of the same
    P_d, v; lam <= 0) only M_c is split at lam, and the other modes' H = P_f - lam P_bi is
    formed from their fixed split: the same values, to the bit (tested)."""
    if fixed is None:
        return hamiltonian_table(vp, P_d, v, lam).H
    assert MC == 0 and FIXED_MODES == (1, 2, 3), "M_c first, then the fixed modes"
    lam = jnp.broadcast_to(lam, jnp.shape(P_d))
    H_c = jax.vmap(lambda P_d, v, lam: mode_gear_split(vp, P_d, v, lam, (MC,)).H)(P_d, v, lam)
    H_f = jnp.where(fixed.feasible, fixed.P_f - lam[:, None, None] * fixed.P_bi, jnp.inf)
    return jnp.concatenate([H_c, H_f], axis=1)


def optimal_mode_gear(split: Split):
    """Minimise H over (M, G) without switching costs (eqs. 36, 42).

    split: Split of shape (..., 4, G) -> (H*, mode index, gear index (0-based)), each (...).
    Ties go to the lowest flat index (combined before engine before motor before open, low gear
    first). H* = +inf where nothing is feasible.
    """
    flat = split.H.reshape(split.H.shape[:-2] + (-1,))
    i = jnp.argmin(flat, axis=-1)
    n_g = split.H.shape[-1]
    return jnp.min(flat, axis=-1), i // n_g, i % n_g


# ------------------------------------------------------------------- guards (eqs. 37-41)
class Guards(NamedTuple):
    """The guards of Figure 9 at gearbox speed w: B1, B2 are lambda_b values, B3, B4, B5 are
    P_d values (W) at the given lambda_b. Shapes broadcast from (w, lam)."""

    B1: jax.Array
    B2: jax.Array
    B3: jax.Array
    B4: jax.Array
    B5: jax.Array


def explicit_hamiltonians(vp: VehicleParams, P_d, w, lam):
    """Table 6 in closed form, limits ignored: (H_c, H_e, H_m, P_b_c) at gearbox speed w.

    H_c, H_e, H_m: the minimised Hamiltonians of combined, engine-only and motor-only (W), with
    the engine delivering more than its friction (fuel active), the motor discharging in M_m
    (P_d > P_m0) and no power limit active; P_b_c: the optimal battery power of M_c (Table 6:
    discharge branch for lambda_b > -eta_m/eta_e, charge branch for lambda_b <
    -1/(eta_e eta_m), zero in between). Valid where `interior_region` holds.
    """
    eta, eta_m, beta = vp.eta_e, vp.eta_m, vp.beta
    pm0 = pt.motor_friction(vp, w)
    pe0 = pt.engine_friction(vp, w)
    H_e = (P_d - pe0) / eta
    p_dis = -(lam + eta_m / eta) / (2 * beta * lam)
    p_chg = -(lam + 1 / (eta * eta_m)) / (2 * beta * lam)
    P_b_c = jnp.where(p_dis > 0, p_dis, jnp.where(p_chg < 0, p_chg, 0.0))
    P_m_c = pm0 + jnp.where(P_b_c > 0, eta_m * P_b_c, P_b_c / eta_m)
    H_c = (P_d - P_m_c - pe0) / eta - lam * (P_b_c + beta * P_b_c**2)
    p_m = (P_d - pm0) / eta_m
    H_m = -lam * (p_m + beta * p_m**2)
    return H_c, H_e, H_m, P_b_c


def guards(vp: VehicleParams, w, lam) -> Guards:
    """Guards B1..B5 of the optimal mode map (eqs. 37-41, derived again) at gearbox speed w.

    Notation: eta = eta_e, eta_m, beta; P_m0 = P_m0(w) <= 0 and P_e0 = P_e0(w) <= 0 the motor
    and engine friction at w; lambda = lambda_b < 0; P_b > 0 discharges. In the region where
    the engine delivers more than its friction (fuel active) and no power limit is active,
    Table 6 and eqs. 1, 4, 7 give (see `explicit_hamiltonians`)

        H_e = (P_d - P_e0) / eta                                       (P_b = 0)
        H_c = H_e - P_m0 / eta + c^2 / (4 beta lambda),   c = lambda + eta_m / eta
              (discharge, P_b = P_dis = -c / (2 beta lambda) > 0, i.e. lambda > -eta_m / eta)
        H_c = H_e - P_m0 / eta + d^2 / (4 beta lambda),   d = lambda + 1 / (eta eta_m)
              (charge, P_b = P_chg = -d / (2 beta lambda) <= 0, lambda <= -1 / (eta eta_m))
        H_c = H_e - P_m0 / eta                             (P_b = 0 in between: M_c loses)
        H_m = -lambda (p + beta p^2),   p = (P_d - P_m0) / eta_m > 0

    B1, B2 (M_c = M_e, independent of P_d): c^2 = 4 beta lambda P_m0 / eta, resp. with d,
    a quadratic in lambda whose root inside the discharge (charge) region is

        B1 = (-eta_m + 2 beta P_m0 + 2 sqrt(beta P_m0 (beta P_m0 - eta_m))) / eta
        B2 = -1/(eta eta_m) + 2 beta P_m0 / eta - (2/eta) sqrt(beta P_m0 (beta P_m0 - 1/eta_m))

    B1 is eq. 37 as printed. Eq. 38 as printed divides its square-root term by eta eta_m;
    the derivation gives eta sqrt(eta_m) (the form above), and the property tests (equal
    Hamiltonians at the guard) confirm it. M_c wins for lambda > B1 and
    lambda < B2, M_e for B2 < lambda < B1. With P_m0 = 0 they collapse to -eta_m/eta and
    -1/(eta eta_m).

    B3, B4, B5 (M_m against M_c or M_e, functions of P_d): in terms of p, H_m - H_other is a
    convex quadratic; M_m wins between its roots and the upper root is the guard (the lower
    root lies where the engine would run below its friction, outside the region):

        M_m = M_c (discharge), lambda > B1:   (p - P_dis)^2 = P_e0 / (eta beta lambda)
            B3: P_d = P_m0 + eta_m (P_dis + sqrt(P_e0 / (eta beta lambda)))            (eq. 39)
        M_m = M_e, B2 < lambda < B1:   beta lambda p^2 + c p + (P_m0 - P_e0) / eta = 0
            B4: P_d = P_m0 + eta_m (-c - sqrt(c^2 - 4 beta lambda (P_m0 - P_e0) / eta))
                                   / (2 beta lambda)                                   (eq. 40)
        M_m = M_c (charge), lambda < B2:
            beta lambda p^2 + c p - P_e0 / eta + d^2 / (4 beta lambda) = 0
            B5: P_d = P_m0 + eta_m (-c - sqrt(c^2 - d^2 + 4 beta lambda P_e0 / eta))
                                   / (2 beta lambda)                                   (eq. 41)

    These are eqs. 39-41 with the lost symbols restored: P_0 = P_e0 (engine friction) and
    lambda_1 = lambda_b. M_m wins for P_d below the guard of the lambda_b region. Each guard
    is returned for every lambda (NaN where its square root is negative); `closed_form_mode`
    picks the one that applies. w: () or array (rad/s); lam: () or array.
    """
    eta, eta_m, beta = vp.eta_e, vp.eta_m, vp.beta
    pm0 = pt.motor_friction(vp, w)
    pe0 = pt.engine_friction(vp, w)
    bp = beta * pm0
    B1 = (-eta_m + 2 * bp + 2 * jnp.sqrt(bp * (bp - eta_m))) / eta
    B2 = -1 / (eta * eta_m) + 2 * bp / eta - (2 / eta) * jnp.sqrt(bp * (bp - 1 / eta_m))
    c = lam + eta_m / eta
    d = lam + 1 / (eta * eta_m)
    bl = beta * lam
    p_dis = -c / (2 * bl)
    B3 = pm0 + eta_m * (p_dis + jnp.sqrt(pe0 / (eta * bl)))
    B4 = pm0 + eta_m * (-c - jnp.sqrt(c * c - 4 * bl * (pm0 - pe0) / eta)) / (2 * bl)
    B5 = pm0 + eta_m * (-c - jnp.sqrt(c * c - d * d + 4 * bl * pe0 / eta)) / (2 * bl)
    return Guards(B1=B1, B2=B2, B3=B3, B4=B4, B5=B5)


def closed_form_mode(vp: VehicleParams, P_d, w, lam):
    """Optimal mode index (MC, ME or MM) from the guards alone, at gearbox speed w.

    M_c if lambda_b > B1 or lambda_b < B2, else M_e; M_m instead when P_d is below the P_d
    guard of that lambda_b region (B3, B4 or B5). Exact only inside `interior_region`: the
    engine above its friction, the motor discharging in M_m, no component or speed limit
    active, P_d > 0 (the open mode is then infeasible). Outside it, use `mode_gear_split`.
    """
    g = guards(vp, w, lam)
    ce_best = jnp.where((lam > g.B1) | (lam < g.B2), MC, ME)
    pd_guard = jnp.where(lam > g.B1, g.B3, jnp.where(lam < g.B2, g.B5, g.B4))
    return jnp.where(P_d < pd_guard, MM, ce_best)


def interior_region(vp: VehicleParams, P_d, w, lam):
    """Where `closed_form_mode` and `explicit_hamiltonians` are exact (bool).

    P_d > 0, lambda_b < 0; w inside the engine's connected speed range and below the motor's
    top speed; in M_c the Table 6 optimum keeps the motor within its power limit and the
    engine strictly above its friction and within its full-load power; in M_e the engine
    likewise; in M_m the motor can deliver P_d.
    """
    _, _, _, P_b_c = explicit_hamiltonians(vp, P_d, w, lam)
    pm0 = pt.motor_friction(vp, w)
    pe0 = pt.engine_friction(vp, w)
    _, pe_max = pt.engine_power_limits(vp, w)
    m_lim = pt.motor_power_limit(vp, w)
    P_m_c = pm0 + jnp.where(P_b_c > 0, vp.eta_m * P_b_c, P_b_c / vp.eta_m)
    P_e_c = P_d - P_m_c
    ok = (P_d > 0) & (lam < 0) & (w >= vp.we_min) & (w <= vp.we_max) & (w <= vp.wm_max)
    ok &= (jnp.abs(P_m_c) <= m_lim) & (P_e_c > pe0) & (P_e_c <= pe_max)
    ok &= (P_d > pe0) & (P_d <= pe_max) & (P_d <= m_lim) & (vp.has_motor > 0.5)
    return ok
