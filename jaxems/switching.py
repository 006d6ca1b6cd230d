"""Switching costs of Appendix C: eps_M (mode switch) and eps_G (gear switch), eqs. A15-A22.

A switch of mode and/or gear costs (in fuel-equivalent joules)

    eps = c_s (synchronisation, A17-A19) + c_t (traction interruption, A20-A22).

Synchronisation (A17-A19). A component (engine CE, motor MG) runs at the gearbox input speed w
when connected and stands still when not. Its rotational energy is U_c = 1/2 I_c w_c^2. A switch
from state (M, G) to (M', G') changes w_c from x_c w(G) to x'_c w(G') (x_c = 1 if connected).
Following the paper's assumptions (accelerating costs energy, decelerating recovers none) the
energy to supply is counted per component,

    dU = sum_c max(0, U_c' - U_c),          c_s = -lambda_b dU      (lambda_b < 0)

which reproduces every entry of Table A1 (e.g. M_e -> M_m starts the motor: 16 kJ, although the
engine that stops holds more energy). For a switch of mode *and* gear this is the energy that
brings each component to its final speed: equal to doing the gear change and the mode change
one after the other in the cheaper order, so eps_M + eps_G of eq. 45 is well defined.
With ``averaged`` = 1 each linked pair of events (start/stop, down/upshift) shares its cost:
c_s = -lambda_b sum_c |U_c' - U_c| / 2 (the "avg" column of Table A1; the paper argues this
balances decisions when a short horizon sees only one of the two events). Values between 0
and 1 blend the two linearly. The full-horizon DP sees both events, so its default is the
direction cost (``averaged`` = 0); receding-horizon users may prefer 1.

Traction interruption (A20-A22), with our sign convention (F_0 = road load, a resistance,
positive uphill; the paper's F_0 is the net force, of opposite sign): during an open driveline
of tau seconds (tau = dt_M for a mode switch, dt_G for a gear switch) the truck decelerates at
F_0 / m from v_0 to v_1 = v_0 - F_0 tau / m, then recovers at the largest driveline force
F_max of the state after the switch in t_r = F_0 tau / (F_max - F_0) (the corrected A21). The
time loss is dt_t = (s_2 - s_0) / v_0 - (tau + t_r) < 0 and c_t = lambda_t dt_t with lambda_t
< 0 (default -25 kJ/s). When the driveline saturates (F_0 >= F_max) the speed is not recovered
and c_t = lambda_k 1/2 m (v_1^2 - v_0^2) (lambda_k < 0, fuel J per J of kinetic energy). Downhill
(F_0 < 0) the truck gains speed while open; that surplus kinetic energy has to be braked away,
priced the same way: c_t = -lambda_k 1/2 m |v_1^2 - v_0^2|. A switch into the open mode M_o
carries no traction cost (the driveline is meant to be open). A switch that changes mode and
gear is one open-driveline event of max(dt_M, dt_G): its traction cost is counted once.
Below ``v_min`` (m/s) the time-loss formula uses v_min (F = P / v is singular at standstill).

State index convention (shared with Level 1 and the DP): s = mode * n_gears + gear, modes
0 = M_c, 1 = M_e, 2 = M_m, 3 = M_o, gear index 0 = gear 1.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax.numpy as jnp
import numpy as np

from . import powertrain as pt
from .levels.powersplit import ENGINE_CONNECTED, MO, MODE_SHORT, MOTOR_CONNECTED, N_MODES
from .params import RPM, VehicleParams


class SwitchCostParams(NamedTuple):
    """Parameters of the switching costs; array leaves (a sweep over them does not recompile).

    lambda_t: J/s (< 0) value of time, default -25 kJ/s (Table A2); lambda_k: - (< 0) value of
    kinetic energy in fuel joules per joule, default -2.2 (about 1/eta_e: kinetic energy is
    restored by the engine); averaged: 0 direction costs, 1 averaged linked events (Table A1
    avg column), in between a blend; weight: multiplies every switching cost (0 switches
    them off); v_min: m/s floor of the speed in the time-loss formula.
    """

    lambda_t: Any = -25e3
    lambda_k: Any = -2.2
    averaged: Any = 0.0
    weight: Any = 1.0
    v_min: Any = 1.0


# what each field must satisfy: (test, words for the error)
_PARAM_RULES = {
    "lambda_t": (lambda x: x <= 0, "<= 0 (J/s, the value of time)"),
    "lambda_k": (lambda x: x <= 0, "<= 0 (fuel J per J of kinetic energy)"),
    "averaged": (lambda x: 0 <= x <= 1, "in [0, 1]"),
    "weight": (lambda x: x >= 0, ">= 0"),
    "v_min": (lambda x: x > 0, "> 0 (m/s)"),
}


def checked_params(params: SwitchCostParams | None, dtype) -> SwitchCostParams:
    """`params` (None: the defaults) validated, with every leaf a scalar array of `dtype`.

    The host API (`simulate`, `simulate_batch`, Level 1's `level1_full`, `level1_mpc`,
    `level1_batch`) passes switching costs through this, so that
    the jitted strategies see the same leaf types whatever the caller gave (Python floats,
    NumPy scalars): new values never recompile. Raises ValueError naming the field for a
    value that is not a finite scalar or breaks its rule (for example lambda_t > 0).
    """
    params = SwitchCostParams() if params is None else params
    if not isinstance(params, SwitchCostParams):
        raise ValueError(f"switching: a SwitchCostParams expected (got {type(params).__name__})")
    out = {}
    for name, (ok, words) in _PARAM_RULES.items():
        x = np.asarray(getattr(params, name))
        if x.ndim != 0 or x.dtype.kind not in "iuf" or not np.isfinite(x):
            raise ValueError(f"switching.{name}: must be a finite number (got {x!r})")
        if not ok(float(x)):
            raise ValueError(f"switching.{name}: must be {words} (got {float(x)!r})")
        out[name] = np.asarray(x, dtype)  # NumPy: no device array before map_batch's devices
    return SwitchCostParams(**out)


def mode_flags(dtype=jnp.float64):
    """(engine connected, motor connected) per mode as float arrays of shape (4,)."""
    return jnp.asarray(ENGINE_CONNECTED, dtype), jnp.asarray(MOTOR_CONNECTED, dtype)


def sync_weights(vp: VehicleParams, averaged):
    """Per-component weights (u_e, d_e, u_m, d_m) (kg m^2) of the synchronisation energy.

    The energy of component c is u_c max(0, x' w'^2 - x w^2) + d_c max(0, x w^2 - x' w'^2):
    direction costs u = I/2, d = 0; averaged costs u = d = I/4; linear blend in between.
    """
    a = jnp.asarray(averaged)
    u_e, d_e = 0.5 * vp.I_e * (1.0 - 0.5 * a), 0.25 * vp.I_e * a
    u_m, d_m = 0.5 * vp.I_m * (1.0 - 0.5 * a), 0.25 * vp.I_m * a
    return u_e, d_e, u_m, d_m


def sync_energy(vp: VehicleParams, ce0, cm0, w0, ce1, cm1, w1, averaged=0.0):
    """Synchronisation energy (J, >= 0) of a switch, eq. A17 counted per component.

    (ce0, cm0, w0): engine / motor connected (0/1) and gearbox input speed (rad/s) before,
    (ce1, cm1, w1) after. Broadcasts.
    """
    u_e, d_e, u_m, d_m = sync_weights(vp, averaged)
    de = ce1 * w1 * w1 - ce0 * w0 * w0
    dm = cm1 * w1 * w1 - cm0 * w0 * w0
    return (
        u_e * jnp.maximum(de, 0.0)
        + d_e * jnp.maximum(-de, 0.0)
        + u_m * jnp.maximum(dm, 0.0)
        + d_m * jnp.maximum(-dm, 0.0)
    )


def sync_cost_matrix(vp: VehicleParams, v, lam, averaged=0.0):
    """Synchronisation cost -lambda_b dU (J) between all states: (S, S), S = 4 * n_gears.

    v: vehicle speed (m/s), lam: lambda_b; both scalars. [s, s'] is the cost of s -> s'.
    """
    w = pt.shaft_speeds(vp, v)  # (G,)
    n_g = w.shape[-1]
    ce, cm = mode_flags(w.dtype)
    ce_s = jnp.repeat(ce, n_g)
    cm_s = jnp.repeat(cm, n_g)
    w_s = jnp.tile(w, N_MODES)
    E = sync_energy(
        vp,
        ce_s[:, None],
        cm_s[:, None],
        w_s[:, None],
        ce_s[None],
        cm_s[None],
        w_s[None],
        averaged,
    )
    return -lam * E


# --------------------------------------------------------------------- traction interruption
def max_driveline_force(vp: VehicleParams, v, v_min=1.0):
    """Largest driveline (traction) force (N) of every mode and gear at speed v: (4, n_gears).

    (engine full-load power if connected and in its speed window + motor power limit if
    connected and below its top speed) / max(v, v_min). Zero for the open mode.
    """
    w = pt.shaft_speeds(vp, v)
    _, pe_max = pt.engine_power_limits(vp, w)
    e_ok = (w >= vp.we_min * (1 - 1e-9)) & (w <= vp.we_max)
    pe = jnp.where(e_ok, pe_max, 0.0)
    pm = jnp.where(w <= vp.wm_max, pt.motor_power_limit(vp, w), 0.0)
    ce, cm = mode_flags(w.dtype)
    P = ce[:, None] * pe[None] + cm[:, None] * pm[None]
    return P / jnp.maximum(v, v_min)


class TractionLoss(NamedTuple):
    """Idealised open-driveline event of Figure A1 (all arrays broadcast from the inputs).

    time_loss_s: -dt_t >= 0 (A20; the paper prints dt_t < 0); speed_loss_mps: v_0 - v_1
    (negative when the truck speeds up downhill); recovery_s: t_2 - t_1; saturated: F_0 >= F_max;
    cost: c_t (J, >= 0), A22.
    """

    time_loss_s: Any
    speed_loss_mps: Any
    recovery_s: Any
    saturated: Any
    cost: Any


def traction_loss(vp: VehicleParams, F0, v, tau, F_max, params: SwitchCostParams) -> TractionLoss:
    """Traction-interruption time loss and cost of one open-driveline event, eqs. A20-A22.

    F0: road load (N, resistance positive), v: speed (m/s), tau: open-driveline time (s), F_max:
    largest driveline force after the switch (N).
    """
    m = vp.mass
    v0 = jnp.maximum(v, params.v_min)
    a0 = -F0 / m
    v1 = jnp.maximum(v0 + a0 * tau, 0.0)
    t_open = jnp.where(a0 < 0, jnp.minimum(tau, v0 / jnp.maximum(-a0, 1e-30)), tau)
    s1 = v0 * t_open + 0.5 * a0 * t_open * t_open
    saturated = jnp.asarray(F0 >= F_max)  # an array also for Python floats (~ on a bool)
    decel = (F0 > 0) & ~saturated
    a2 = jnp.where(decel, (F_max - F0) / m, 1.0)
    t_r = jnp.where(decel, (v0 - v1) / a2, 0.0)
    s2 = s1 + v1 * t_r + 0.5 * a2 * t_r * t_r
    dt_t = jnp.where(decel, s2 / v0 - (tau + t_r), 0.0)  # A20, <= 0
    c_time = params.lambda_t * dt_t
    c_kin = -params.lambda_k * 0.5 * m * jnp.abs(v1 * v1 - v0 * v0)
    cost = jnp.where(decel, c_time, jnp.where(F0 == 0, 0.0, c_kin))
    return TractionLoss(
        time_loss_s=-dt_t,
        speed_loss_mps=v0 - v1,
        recovery_s=t_r,
        saturated=saturated,
        cost=cost,
    )


def open_times(vp: VehicleParams):
    """(3,) seconds of open driveline (eq. 12) of a mode switch only, a gear switch only and
    both (one event of max(dt_M, dt_G)): the rows of `traction_cost_table`."""
    return jnp.stack([vp.dt_M, vp.dt_G, jnp.maximum(vp.dt_M, vp.dt_G)])


def traction_cost_table(vp: VehicleParams, v, grade, params: SwitchCostParams):
    """Traction-interruption cost (J) of switching into each state: (3, S).

    Rows: a mode switch only (tau = dt_M), a gear switch only (tau = dt_G), both (one event of
    max(dt_M, dt_G)). Column s' is the state after the switch; zero for the open mode.
    """
    F0 = pt.road_load(vp, v, grade)
    F_max = max_driveline_force(vp, v, params.v_min)  # (4, G)
    taus = open_times(vp)
    c = traction_loss(vp, F0, v, taus[:, None, None], F_max[None], params).cost  # (3, 4, G)
    c = c + stranded_cost(vp, v, F0, taus)
    c = c.at[:, MO, :].set(0.0)
    return c.reshape(3, -1)


STRANDED_J = 1e9  # cost of switching into a state that cannot run once the switch is done


def stranded_cost(vp: VehicleParams, v, F0, taus):
    """(len(taus), 4, G): STRANDED_J where the state switched into could not run at the speed
    left after the open driveline (v - F0 tau / m, uphill): a connected engine below idle (gear 1
    may slip its clutch). Planning into such a state would leave the plant without traction
    right after the switch, so Level 1 avoids it."""
    v1 = jnp.maximum(v - jnp.maximum(F0, 0.0) * taus / vp.mass, 0.0)  # (K,)
    w1 = pt.shaft_speeds(vp, v1)  # (K, G)
    gear1 = jnp.arange(w1.shape[-1]) == 0
    e_bad = (w1 < vp.we_min * (1 - 1e-9)) & ~gear1 & (v > 0)
    ce, _ = mode_flags(w1.dtype)
    return jnp.where((ce[None, :, None] > 0) & e_bad[:, None, :], STRANDED_J, 0.0)


def switch_cost_matrix(vp: VehicleParams, v, grade, lam, params: SwitchCostParams,
                       extra=None):
    """Dense switching cost eps_M + eps_G (J) between all states at one step: (S, S).

    [s, s'] = weight * (synchronisation(s -> s') + traction(kind, s')) for s != s', 0 on the
    diagonal, where kind is mode-only / gear-only / both. extra: optional (3, S) J per kind and
    state switched into, added to the traction cost (Level 1's `level1.braking_loss`). The
    reference for the structured relaxation of Level 1.
    """
    n_g = vp.gear_ratio.shape[-1]
    S = N_MODES * n_g
    sync = sync_cost_matrix(vp, v, lam, params.averaged)
    trac = traction_cost_table(vp, v, grade, params)  # (3, S)
    trac = trac if extra is None else trac + extra
    mode = jnp.arange(S) // n_g
    gear = jnp.arange(S) % n_g
    dm = mode[:, None] != mode[None]
    dg = gear[:, None] != gear[None]
    t = jnp.where(dm & dg, trac[2][None], jnp.where(dm, trac[0][None], trac[1][None]))
    return jnp.where(dm | dg, params.weight * (sync + t), 0.0)


def eps_M(vp: VehicleParams, v, grade, lam, gear, params: SwitchCostParams):
    """Mode-switch cost eps_M(M -> M') (J) at a fixed gear index: (4, 4), eq. A15."""
    C = switch_cost_matrix(vp, v, grade, lam, params)
    n_g = vp.gear_ratio.shape[-1]
    idx = jnp.arange(N_MODES) * n_g + gear
    return C[idx[:, None], idx[None]]


def eps_G(vp: VehicleParams, v, grade, lam, mode, params: SwitchCostParams):
    """Gear-switch cost eps_G(G -> G') (J) in a fixed mode: (n_gears, n_gears), eq. A16."""
    C = switch_cost_matrix(vp, v, grade, lam, params)
    n_g = vp.gear_ratio.shape[-1]
    idx = mode * n_g + jnp.arange(n_g)
    return C[idx[:, None], idx[None]]


# ---------------------------------------------------------------------------- paper's tables
# Table A1 of the paper (kJ, lambda_b = -2.2): direction costs and averages of linked events
PAPER_A1 = {
    "G_down_Mm": 10, "G_down_Me": 20, "G_down_Mc": 30, "G_up": 0,
    "Me->Mm": 16, "Mm->Me": 31, "Me->Mc": 16, "Mc->Me": 0, "Mm->Mc": 31, "Mc->Mm": 0,
}
PAPER_A1_AVG = {"Me->Mm": 24, "Mm->Me": 24, "Me->Mc": 8, "Mc->Me": 8, "Mm->Mc": 16, "Mc->Mm": 16}

A1_TRANSITIONS = (
    "G_down_Mm",
    "G_down_Me",
    "G_down_Mc",
    "G_up",
    "Me->Mm",
    "Mm->Me",
    "Me->Mc",
    "Mc->Me",
    "Mm->Mc",
    "Mc->Mm",
)


def table_a1(vp: VehicleParams, lam=-2.2, w_conn_rpm=930.0, w_down_rpm=1200.0):
    """Synchronisation costs of Table A1 (J): dict transition -> (direction cost, avg cost).

    Speeds as in the paper: 0 when disconnected, w_conn_rpm when connected, w_down_rpm after a
    downshift (an upshift goes back from w_down_rpm to w_conn_rpm). The avg cost is the mean
    over the linked pair of events (`averaged` = 1).
    """
    w0, w1 = w_conn_rpm * RPM, w_down_rpm * RPM
    flags = {k: (ENGINE_CONNECTED[i], MOTOR_CONNECTED[i]) for i, k in enumerate(MODE_SHORT)}
    out = {}

    def cost(a, b, wa, wb, averaged):
        (ce0, cm0), (ce1, cm1) = flags[a], flags[b]
        E = sync_energy(vp, float(ce0), float(cm0), wa, float(ce1), float(cm1), wb, averaged)
        return float(-lam * E)

    for m in ("Mm", "Me", "Mc"):
        out[f"G_down_{m}"] = (cost(m, m, w0, w1, 0.0), cost(m, m, w0, w1, 1.0))
    out["G_up"] = (cost("Mc", "Mc", w1, w0, 0.0), cost("Mc", "Mc", w1, w0, 1.0))
    for a, b in (
        ("Me", "Mm"),
        ("Mm", "Me"),
        ("Me", "Mc"),
        ("Mc", "Me"),
        ("Mm", "Mc"),
        ("Mc", "Mm"),
    ):
        out[f"{a}->{b}"] = (cost(a, b, w0, w0, 0.0), cost(a, b, w0, w0, 1.0))
    return out


def table_a2(
    vp: VehicleParams,
    slopes_pct=(0.0, 6.0, 12.0),
    speed_mps=25 / 3.6,
    tau_s=1.0,
    params: SwitchCostParams | None = None,
    mode: int = 1,
):
    """Traction-interruption rows of Table A2: list of dicts per slope.

    Each row: slope_pct, speed_loss_mps (v_0 - v_1), time_loss_s (-dt_t), cost_kJ, F0_N (road
    load), F_max_N (the largest driveline force of ``mode`` over all gears at that speed: the
    recovery force), saturated. Default mode 1 = engine-only (the paper's uphill mode).
    """
    params = SwitchCostParams() if params is None else params
    F_max = float(jnp.max(max_driveline_force(vp, speed_mps, params.v_min)[mode]))
    rows = []
    for slope in slopes_pct:
        F0 = float(pt.road_load(vp, speed_mps, slope / 100.0))
        r = traction_loss(vp, F0, speed_mps, tau_s, F_max, params)
        rows.append(
            {
                "slope_pct": float(slope),
                "speed_loss_mps": float(r.speed_loss_mps),
                "time_loss_s": float(r.time_loss_s),
                "cost_kJ": float(r.cost) / 1e3,
                "F0_N": F0,
                "F_max_N": F_max,
                "saturated": bool(r.saturated),
            }
        )
    return rows
