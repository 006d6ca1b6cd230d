"""Component models of the parallel hybrid truck (paper section 2), as pure JAX functions.

Sign conventions: powers are positive towards the road (P_e, P_m, P_d > 0 drive the vehicle);
P_b > 0 discharges the battery; road-load forces are resistances, positive when they oppose
motion (air drag, rolling resistance, and grade on a climb). This resolves the sign ambiguity
of eq. 14, which we write as  m dv/dt = F_d - F_0  with F_0 = F_a + F_r + F_g.

Every function takes `vp: VehicleParams` first and works on scalars or broadcastable arrays.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from .params import VehicleParams


# ------------------------------------------------------------------------------- interpolation
def interp_at(r, x, xp, fp):
    """`jnp.interp(x, xp, fp)` (the same arithmetic, to the last bit) given r, the index
    `searchsorted(xp, x, side="right")` (x of any shape, xp and fp (N,))."""
    xp, fp = jnp.asarray(xp), jnp.asarray(fp)
    i = jnp.clip(r, 1, xp.shape[0] - 1)
    df = fp[i] - fp[i - 1]
    dx = xp[i] - xp[i - 1]
    delta = x - xp[i - 1]
    dx0 = jnp.abs(dx) <= np.spacing(np.finfo(xp.dtype).eps)
    f = jnp.where(dx0, fp[i - 1], fp[i - 1] + (delta / jnp.where(dx0, 1, dx)) * df)
    return jnp.where(x > xp[-1], fp[-1], jnp.where(x < xp[0], fp[0], f))


def interp(x, xp, fp):
    """`jnp.interp(x, xp, fp)` for a short xp (a capability curve's few points): the search
    compares x with every point at once (`searchsorted(method="compare_all")`), one fused
    kernel, where jnp.interp's binary search is a loop of a few kernels per halving; inside
    the plant's step (a scalar x) that loop's overhead was most of the step's time."""
    return interp_at(jnp.searchsorted(xp, x, side="right", method="compare_all"), x, xp, fp)


# ---------------------------------------------------------------------------- engine (eqs. 1-3)
def engine_friction(vp: VehicleParams, w):
    """P_e0(w) <= 0 (W): engine friction at crank speed w (rad/s)."""
    return -(vp.e0_lin * w + vp.e0_quad * w * w)


def engine_power_limits(vp: VehicleParams, w):
    """(P_e_min, P_e_max) (W) at crank speed w: engine-brake and full-load power, eq. 2."""
    t_max = interp(w, vp.te_max_w, vp.te_max)
    t_min = interp(w, vp.te_min_w, vp.te_min)
    return t_min * w, t_max * w


def fuel_power(vp: VehicleParams, P_e, w):
    """P_f >= 0 (W): Willans fuel power for crank power P_e at speed w, eqs. 1 and 3.

    No fuel while the engine delivers no more than its friction (P_e <= P_e0: engine braking).
    """
    return jnp.maximum(P_e - engine_friction(vp, w), 0.0) / vp.eta_e


# ----------------------------------------------------------------------------- motor (eqs. 4-5)
def motor_friction(vp: VehicleParams, w):
    """P_m0(w) <= 0 (W): motor friction at speed w (rad/s); zero when stopped."""
    return -(vp.m0_lin * w + vp.m0_quad * w * w)


def motor_power_limit(vp: VehicleParams, w):
    """|P_m| <= this (W): min(torque limit x w, power limit), the same both ways, eq. 5."""
    return jnp.minimum(vp.tm_max * w, vp.pm_max) * vp.has_motor


def motor_mech_power(vp: VehicleParams, P_b, w):
    """P_m (W) for terminal power P_b, eq. 4: eta_m when motoring, 1/eta_m when generating."""
    return motor_friction(vp, w) + jnp.where(P_b > 0, vp.eta_m * P_b, P_b / vp.eta_m)


def motor_elec_power(vp: VehicleParams, P_m, w):
    """P_b (W) that gives mechanical output P_m at speed w: the inverse of eq. 4."""
    d = P_m - motor_friction(vp, w)
    return jnp.where(d > 0, d / vp.eta_m, d * vp.eta_m)


# ------------------------------------------------------------------------- battery (eqs. 6-7)
def battery_internal(vp: VehicleParams, P_b):
    """P_bi = P_b + beta P_b^2 (W): the rate at which E_b decreases, eq. 7."""
    return P_b + vp.beta * P_b * P_b


# ------------------------------------------------------------------------ gearbox (eqs. 10-11)
def shaft_speeds(vp: VehicleParams, v):
    """Gearbox input speed (rad/s) in every gear at vehicle speed v (m/s): (..., n_gears)."""
    return vp.gear_ratio * vp.r_d * jnp.asarray(v)[..., None]


# ------------------------------------------------------------------------ vehicle (eqs. 14-18)
def slope_angle(grade):
    """Road inclination alpha (rad) from a gradient (rise over run, e.g. 0.06 for 6 %)."""
    return jnp.arctan(grade)


def road_load(vp: VehicleParams, v, grade):
    """F_0 (N): air drag + rolling resistance + grade force, positive when resisting motion.

    `grade` is rise over run (0.06 = 6 %).
    """
    alpha = slope_angle(grade)
    f_air = 0.5 * vp.c_w * vp.area * vp.rho * v * v
    f_roll = vp.mass * vp.g * vp.c_r * jnp.cos(alpha)
    f_grade = vp.mass * vp.g * jnp.sin(alpha)
    return f_air + f_roll + f_grade


def fuel_litres(vp: VehicleParams, E_f):
    """Fuel volume (l) of fuel energy E_f (J)."""
    return E_f / vp.lhv / vp.fuel_density
