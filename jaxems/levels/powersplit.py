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


def _split_one(vp: VehicleParams, P_d, w, lam, ce, cm, launch):
    """Minimise H over P_b for one mode (ce, cm flags) at gearbox speed w. Scalars in and out."""
    dtype = jnp.result_type(P_d, w, lam, float)
    ce = jnp.asarray(ce)
    needs_motor = jnp.asarray(cm)
    cm = needs_motor & (vp.has_motor > 0.5)  # a conventional truck has no motor modes
    # engine: speed, slip factor k, output range [e_lo, e_hi] and friction at the crank
    slip = launch & (w < vp.we_min)
    we = jnp.where(slip, vp.we_min, w)
    k = jnp.where(slip, _safe_div(vp.we_min, w), 1.0)
    pe_min, pe_max = pt.engine_power_limits(vp, we)
    e_ok = (we >= vp.we_min * (1 - 1e-9)) & (we <= vp.we_max) & (w > 0)
    e_lo = jnp.where(ce, _safe_div(pe_min, k), 0.0)
    e_hi = jnp.where(ce, _safe_div(pe_max, k), 0.0)
    pe0 = jnp.where(ce, pt.engine_friction(vp, we), 0.0)
    # motor: friction and symmetric power limit (zero when open)
    m_ok = w <= vp.wm_max
    m_lim = jnp.where(cm, pt.motor_power_limit(vp, w), 0.0)
    pm0 = jnp.where(cm, pt.motor_friction(vp, w), 0.0)

    def pb_of_pm(P_m):  # inverse of eq. 4 (zero when the motor is open)
        d = P_m - pm0
        return jnp.where(cm, jnp.where(d > 0, d / vp.eta_m, d * vp.eta_m), 0.0)

    def pm_of_pb(P_b):  # eq. 4
        return jnp.where(cm, pm0 + jnp.where(P_b > 0, vp.eta_m * P_b, P_b / vp.eta_m), 0.0)

    pm_lo = jnp.maximum(-m_lim, P_d - e_hi)
    pm_hi = m_lim
    feasible = (pm_lo <= pm_hi) & jnp.where(ce, e_ok, True) & jnp.where(cm, m_ok, True)
    feasible = feasible & (cm | ~needs_motor)
    pm_lo = jnp.minimum(pm_lo, pm_hi)
    lo, hi = pb_of_pm(pm_lo), pb_of_pm(pm_hi)

    two_bl = 2.0 * vp.beta * lam
    stat_dis = -_safe_div(lam + k * vp.eta_m / vp.eta_e, two_bl)
    stat_chg = -_safe_div(lam + k / (vp.eta_e * vp.eta_m), two_bl)
    kink_fuel = pb_of_pm(P_d - _safe_div(pe0, k))
    kink_brake = pb_of_pm(P_d - e_lo)
    cands = jnp.stack(
        [lo, hi, jnp.zeros_like(lo), stat_dis, stat_chg, kink_fuel, kink_brake,
         jnp.full_like(lo, -0.5 / vp.beta)]
    ).astype(dtype)
    cands = jnp.clip(cands, lo, hi)

    P_m = pm_of_pb(cands)
    P_out = jnp.where(ce, jnp.clip(P_d - P_m, e_lo, e_hi), 0.0)
    P_e = k * P_out
    P_f = jnp.where(ce, jnp.maximum(P_e - pe0, 0.0) / vp.eta_e, 0.0)
    H_c = P_f - lam * pt.battery_internal(vp, cands)
    i = jnp.argmin(H_c)
    H = jnp.where(feasible, H_c[i], jnp.inf)
    P_brake = jnp.minimum(P_d - P_out[i] - P_m[i], 0.0)
    z = jnp.zeros_like(H)
    pick = lambda x: jnp.where(feasible, x, z)  # noqa: E731
    return Split(
        H=H, P_b=pick(cands[i]), P_e=pick(P_e[i]), P_m=pick(P_m[i]), P_f=pick(P_f[i]),
        P_brake=pick(P_brake), w=w, feasible=feasible,
    )


def mode_gear_split(vp: VehicleParams, P_d, v, lam) -> Split:
    """The optimal split of every (mode, gear) at one time step: `Split` of shape (4, n_gears).

    P_d: driveline power demand (W), v: vehicle speed (m/s), lam: battery costate lambda_b (-),
    all scalars. `vmap` over the (M, G) grid; map over time with `jax.vmap` at the edge.
    """
    w = pt.shaft_speeds(vp, v)  # (G,)
    n_g = w.shape[-1]
    ce = jnp.array(ENGINE_CONNECTED)
    cm = jnp.array(MOTOR_CONNECTED)
    launch = jnp.arange(n_g) == 0  # gear 1 may slip its clutch below idle speed
    per_gear = jax.vmap(_split_one, in_axes=(None, None, 0, None, None, None, 0))
    per_mode = jax.vmap(per_gear, in_axes=(None, None, None, None, 0, 0, None))
    return per_mode(vp, P_d, w, lam, ce, cm, launch)


def hamiltonian_table(vp: VehicleParams, P_d, v, lam) -> Split:
    """`mode_gear_split` over a time grid: P_d, v: (T,), lam: () or (T,) -> Split of (T, 4, G)."""
    lam = jnp.broadcast_to(lam, jnp.shape(P_d))
    return jax.vmap(mode_gear_split, in_axes=(None, 0, 0, 0))(vp, P_d, v, lam)


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
