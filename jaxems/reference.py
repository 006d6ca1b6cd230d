"""Plain NumPy references of the jaxems kernels: what the tests compare the kernels with.

This module is NOT for production. It restates each level in float64 NumPy, written from the
paper's equations with Python loops and brute force where that keeps it obviously right, so
that the JAX kernels (`jaxems.levels`, `jaxems.switching`, `jaxems.dp`) can be checked against
something independent of their algorithms. It is also the baseline of
``benchmarks/bench_reference.py`` (speed-up of the jitted, vmapped kernels over this code).

Contents (shapes for one route and one vehicle; T time steps, S = 4 * n_gears states):

- Level 3 (section 6): `ref_profile` (forward and backward passes over the distance grid, a
  loop per node), `ref_pieces` (the motion as standing / constant-acceleration pieces),
  `ref_time_grid` (per time step: distance, mean power by Gauss quadrature over the pieces,
  speed at t_k) and `ref_prediction` (the whole time grid: v, P_d, grade, mask, ...).
- Level 1 split (section 4): `ref_split` minimises H = P_f - lambda_b P_bi over a uniform grid
  of battery powers spanning exactly each (mode, gear)'s feasible interval (one step);
  `split_table` does the same over many steps on a grid refined around its minimum (H is
  convex in P_b for lambda_b < 0, so the minimum of a grid lies within one spacing of the true
  one): `n_grid` points, `levels` refinements, each shrinking the spacing by (n_grid - 1) / 2,
  plus the exact points P_b = 0 and the interval ends. With the defaults (33 points, 12
  levels) the final spacing is below 1e-9 W. This is a brute-force search, not the kernel's
  analytic candidate search.
- Switching costs (Appendix C): `ref_traction_table` (traction interruption per target state)
  and `ref_cost_matrix` (synchronisation per component + one traction event per switch).
- Dynamic programming: `viterbi_path` (plain loop over steps, back-pointers; ties: stay,
  then the lowest source state; final state: the lowest index among the minima) and
  `numpy_viterbi` (its cost).
- Level 2 (section 5): `ref_gears` (the gear rule of `battery.select_gears`), `ref_steps`
  (the best mode at the step's gear for a costate), `ref_end` (E_b(t_f) for a constant
  costate), `ref_bisect` (bisection on lambda_b, no battery limits), `ref_fuel_power` and
  `ref_dp` (the minimal fuel by DP over a battery-energy grid, with limits).
- The plant: `ref_track` (what it reads of the route and the reference, by loops) and
  `ref_plant` (the closed loop's step as a loop over steps under a scripted
  controller: reference speed by position, stops, mean gradient, Level 0's state, open
  driveline, synchronisation, the split, battery limits and the final braking's cap, motion,
  totals).
- dp-bound: `ref_bound_dp` (its DP over an E_b grid with interpolation, as loops) and
  `brute_bound` (every sequence of states and candidates, for tiny problems).
- Plans on the plant: `ref_battery_path` (a plan's battery energy piece by piece, each piece
  from Level 2's start value, held within the battery's limits step by step) and
  `ref_plan_energy` (each step's battery energy change: synchronisation, open driveline).
- `reference_plan`: iteration 0 of the multilevel strategy's planning pipeline, the same stages
  as `kernel_plan` (which runs them through the JAX kernels): Level 3 prediction -> Level 2
  costate by bisection (charge sustaining, no battery limits, gears from the constant engine
  speed w_pred) -> Level 1 Hamiltonian table over mode x gear per step + Viterbi with switching
  costs. The strategy itself adds what this pipeline leaves out (battery limits by I1 pieces,
  Level 2's I2b sides at guards, the charge-sustaining shift of Level 1's costate, the plant).
- `kernel_plan` (stages `kernel_level3`, `kernel_level2`, `kernel_level1`) runs the same
  stages through the JAX kernels, and `compare_plans` measures the agreement of the two.

Where the loops are: Level 3 loops over nodes and time steps, the Viterbi DP over time steps
(building each step's cost matrix), the split search and the Level 2 bisection over modes and
refinement levels with NumPy arrays over the time steps (and gears), and the cost matrix is
broadcast over state pairs; on LongHaul (about 5000 steps) `reference_plan` takes 5-9 s on one
core (shared machine), 40-60 % of it the Level 2 bisection.

Conventions follow the kernels: mode indices 0 M_c, 1 M_e, 2 M_m, 3 M_o; gear index 0 is gear
1; state s = mode * n_gears + gear; SI units; lambda_b < 0.
"""

from __future__ import annotations

import math
import time
from types import SimpleNamespace
from typing import Any, NamedTuple

import numpy as np

from .levels.powersplit import ENGINE_CONNECTED, MC, ME, MM, MO, MOTOR_CONNECTED, N_MODES
from .levels.velocity import P_PENALTY_W, V_CRAWL, steps_for
from .params import VehicleParams
from .plant import ESCAPE_MARGIN
from .route import Route, n_nodes
from .switching import STRANDED_J, SwitchCostParams

LAM_BRACKET = (-6.0, -0.3)  # the bisection bracket of `battery.LAM_BRACKET`


# ----------------------------------------------------------------------------- components
def _veh(vp: VehicleParams) -> SimpleNamespace:
    """The vehicle as float64: scalars as Python floats, curves as arrays."""
    out = {}
    for k, x in vp._asdict().items():
        a = np.asarray(x, dtype=np.float64)
        out[k] = float(a) if a.ndim == 0 else a
    return SimpleNamespace(**out)


def road_load(vp, v, grade):
    """F_0 (N) = air drag + rolling resistance + grade force, positive when resisting (eq. 14)."""
    f = vp if isinstance(vp, SimpleNamespace) else _veh(vp)
    a = np.arctan(grade)
    return 0.5 * f.c_w * f.area * f.rho * v * v + f.mass * f.g * (f.c_r * np.cos(a) + np.sin(a))


def _engine_friction(f, w):
    return -(f.e0_lin * w + f.e0_quad * w * w)


def _engine_limits(f, w):
    return np.interp(w, f.te_min_w, f.te_min) * w, np.interp(w, f.te_max_w, f.te_max) * w


def _motor_friction(f, w):
    return -(f.m0_lin * w + f.m0_quad * w * w)


def _motor_limit(f, w):
    return np.minimum(f.tm_max * w, f.pm_max) * f.has_motor


# ------------------------------------------------------------------------------- Level 3
def a_fwd(vp, v, grade, w):
    """Forward-pass acceleration (m/s^2): a = min(a_max, (F_max(v) - F_0) / m), F_max of the
    engine alone at speed w behind a CVT, capped by the peak torque in gear 1, then slowed by
    the upshifts' open driveline where a > 0: a / (1 + k max(a + F_0 / m, 0)),
    k = dt_G / (max(v, v_1) ln r) s per m/s, r the mean ratio step, v_1 gear 1's top speed
    (scalar w and grade; v a scalar or an array)."""
    f = vp if isinstance(vp, SimpleNamespace) else _veh(vp)
    p_max = np.interp(w, f.te_max_w, f.te_max) * w
    f_max = np.minimum(p_max / np.maximum(v, 1e-6), np.max(f.te_max) * f.gear_ratio[0] * f.r_d)
    f0 = road_load(f, v, grade)
    a = np.minimum(f.a_max, (f_max - f0) / f.mass)
    n = len(f.gear_ratio)
    ln_r = abs(math.log(f.gear_ratio[0] / f.gear_ratio[-1])) / (n - 1) if n > 1 else 0.0
    if ln_r <= 1e-9:  # one gear, or gears of one ratio: nothing to shift
        return a
    v1 = f.we_max / (np.max(f.gear_ratio) * f.r_d)
    k = f.dt_G / (np.maximum(v, v1) * ln_r)
    return np.where(a > 0, a / (1.0 + k * np.maximum(a + f0 / f.mass, 0.0)), a)


def ref_profile(route: Route, vp: VehicleParams, w=None):
    """Plain loops of section 6: forward at full traction, backward at a_min, the minimum.

    Returns (v, v_fwd, v_bwd, feasible): (n,) node speeds (m/s) over the n valid nodes and
    whether the forward pass never stalled below the crawl floor away from a stop.
    """
    f = _veh(vp)
    n = n_nodes(route)
    ds = float(route.ds)
    w = np.full(n, f.w_pred) if w is None else np.broadcast_to(w, (n,))
    stop = np.asarray(route.stop)[:n]
    lim = np.minimum(np.asarray(route.vmax, dtype=np.float64)[:n], f.v_cruise)
    lim[stop > 0] = 0.0
    floor = np.where(stop > 0, 0.0, np.minimum(V_CRAWL, lim))
    g = np.asarray(route.grade)[:n]
    vf = np.zeros(n)
    vf[0] = lim[0]
    stalled = False
    for i in range(n - 1):
        a1 = a_fwd(f, vf[i], g[i], w[i])
        vp_ = math.sqrt(max(vf[i] ** 2 + 2 * a1 * ds, 0.0))
        a = min(a1, a_fwd(f, vp_, g[i], w[i]))
        v2 = vf[i] ** 2 + 2 * a * ds
        if a < 0 and v2 < floor[i + 1] ** 2:
            stalled = True
        vf[i + 1] = max(min(lim[i + 1], math.sqrt(max(v2, 0.0))), floor[i + 1])
    vb = np.zeros(n)
    vb[-1] = lim[-1]
    for i in range(n - 2, -1, -1):
        vb[i] = min(lim[i], math.sqrt(vb[i + 1] ** 2 + 2 * f.a_min * ds))
    return np.minimum(vf, vb), vf, vb, not stalled


def ref_pieces(route: Route, v):
    """Motion as pieces (t0, t1, s0, v0, a, grade): standing at stops, constant acceleration
    over each cell (uniform motion at V_CRAWL / 2 when both ends stand still).

    A cell's piece carries the cell's gradient; a stop's piece the gradient of the cell the
    truck arrived by (the first cell at the start), the convention of `velocity.resample` for
    standing steps. Returns (pieces, trip time (s)).
    """
    n = n_nodes(route)
    ds = float(route.ds)
    stop = np.asarray(route.stop)
    g = np.asarray(route.grade)
    pieces, t = [], 0.0
    for i in range(n):
        if stop[i] > 0:
            pieces.append((t, t + stop[i], i * ds, 0.0, 0.0, g[max(i - 1, 0)]))
            t += stop[i]
        if i < n - 1:
            if v[i] + v[i + 1] >= V_CRAWL:
                dtc = 2 * ds / (v[i] + v[i + 1])
                pieces.append((t, t + dtc, i * ds, v[i], (v[i + 1] - v[i]) / dtc, g[i]))
            else:
                dtc = 2 * ds / V_CRAWL
                pieces.append((t, t + dtc, i * ds, ds / dtc, 0.0, g[i]))
            t += dtc
    return pieces, t


def _time_grid(route, vp, v, dt, T):
    """Per step: distance, mean power, speed at t_k, rise and the gradient at t_k; trip time."""
    f = _veh(vp)
    pieces, trip = ref_pieces(route, v)
    t0s = np.array([p[0] for p in pieces])
    xg, wg = np.polynomial.legendre.leggauss(3)
    dist, P, v_at = np.zeros(T), np.zeros(T), np.zeros(T)
    rise, g_at = np.zeros(T), np.zeros(T)
    for k in range(T):
        ta, tb = k * dt, min((k + 1) * dt, trip)
        j = max(int(np.searchsorted(t0s, ta, side="right")) - 1, 0)
        p = pieces[j]
        v_at[k] = p[3] + p[4] * min(max(ta - p[0], 0.0), p[1] - p[0]) if ta < trip else 0.0
        g_at[k] = p[5]
        while j < len(pieces) and pieces[j][0] < tb:
            t0, t1, s0, v0, a, g = pieces[j]
            lo, hi = max(t0, ta), min(t1, tb)
            if hi > lo:
                tau = 0.5 * (hi - lo) * xg + 0.5 * (hi + lo) - t0
                vv = v0 + a * tau
                d = 0.5 * (hi - lo) * np.sum(wg * vv)
                dist[k] += d
                rise[k] += g * d
                P[k] += 0.5 * (hi - lo) * np.sum(wg * (f.mass * a + road_load(f, vv, g)) * vv)
            j += 1
    return dist, P / dt, v_at, rise, g_at, trip


def ref_time_grid(route: Route, vp: VehicleParams, v, dt, T):
    """Per step: distance, mean power int (m a + F_0(v)) v dt / dt by exact Gauss quadrature
    over the pieces (the integrand is a cubic in t), the speed at t_k.

    v: (n,) node speeds (`ref_profile`); returns (dist (T,) m, P (T,) W, v_at (T,) m/s, trip s).
    """
    dist, P, v_at, _, _, trip = _time_grid(route, vp, v, dt, T)
    return dist, P, v_at, trip


class RefPrediction(NamedTuple):
    """Level 3 on the time grid (NumPy); shapes (T,) unless noted.

    v: mean speed over the step (m/s); P_d: mean driveline power (W); grade: mean gradient
    over the step (the gradient at t_k while standing); v_ref: speed at t_k; s: position at
    t_k (m); mask: t_k < trip time; trip_time: () s; feasible: () bool; v_nodes: (n,) node
    speeds; dt: () s.
    """

    v: np.ndarray
    P_d: np.ndarray
    grade: np.ndarray
    v_ref: np.ndarray
    s: np.ndarray
    mask: np.ndarray
    trip_time: float
    feasible: bool
    v_nodes: np.ndarray
    dt: float


def ref_prediction(route: Route, vp: VehicleParams, dt: float = 1.0, n_steps: int | None = None,
                   w=None) -> RefPrediction:
    """Level 3 (section 6) on the uniform time grid, as `velocity.predict_velocity` defines it.

    n_steps: number of steps (default `velocity.steps_for` of the trip); w: () or (n,) engine
    speed (rad/s) of the forward pass (default vp.w_pred). Standing and masked steps have
    v = P_d = 0.
    """
    v_n, _, _, ok = ref_profile(route, vp, w)
    _, trip = ref_pieces(route, v_n)
    T = steps_for(trip, dt) if n_steps is None else int(n_steps)
    dist, P, v_at, rise, g_at, trip = _time_grid(route, vp, v_n, dt, T)
    mask = np.arange(T) * dt < trip
    moving = dist > 1e-9 * float(route.ds)
    grade = np.where(moving, rise / np.where(moving, dist, 1.0), g_at)
    z = np.zeros(T)
    return RefPrediction(
        v=np.where(mask, dist / dt, z), P_d=np.where(mask & moving, P, z),
        grade=np.where(mask, grade, z), v_ref=np.where(mask, v_at, z),
        s=np.concatenate([[0.0], np.cumsum(dist)[:-1]]), mask=mask, trip_time=trip,
        feasible=bool(ok), v_nodes=v_n, dt=float(dt),
    )


# ------------------------------------------------------------------------ Level 1 split
class _Ranges(NamedTuple):
    """What one mode can do at gearbox speed w (arrays of one broadcast shape)."""

    ok: np.ndarray  # the state can run and meets the demand
    cm: bool  # motor connected (and present)
    ce: bool  # engine connected
    k: np.ndarray  # slip factor (crank power per output power)
    pe_lo: np.ndarray  # engine output range at the clutch (W)
    pe_hi: np.ndarray
    pe0: np.ndarray  # engine friction at the crank (W, <= 0)
    pm0: np.ndarray  # motor friction (W, <= 0)
    pb_lo: np.ndarray  # feasible battery power interval (W)
    pb_hi: np.ndarray
    idle: float  # fuel power (W) of a declutched idling engine (conventional truck)


def _pb_of_pm(f, pm0, P_m):
    d = P_m - pm0
    return np.where(d > 0, d / f.eta_m, d * f.eta_m)


def _pm_of_pb(f, pm0, P_b):
    """Motor output for battery power P_b (eq. 4), motor friction pm0."""
    return pm0 + np.where(P_b > 0, f.eta_m * P_b, P_b / f.eta_m)


def _caps(f, mode: int, w, launch):
    """What `mode` (index) can do at gearbox speed w (rad/s), whatever the demand: (runs,
    motor connected, engine connected, slip factor k, engine output range pe_lo, pe_hi at the
    clutch, engine friction pe0, motor limit m_lim, motor friction pm0). A connected engine
    needs w in [we_min, we_max] (in gear 1 below idle it runs at we_min with a slipping clutch
    that cannot brake: crank power = k * output, k = we_min / w), a connected motor w <=
    wm_max."""
    ce, needs_motor = ENGINE_CONNECTED[mode], MOTOR_CONNECTED[mode]
    cm = needs_motor and f.has_motor >= 0.5
    w, launch = np.broadcast_arrays(np.asarray(w, float), launch)
    zero = np.zeros(w.shape)
    ok = np.ones(w.shape, bool) if (cm or not needs_motor) else np.zeros(w.shape, bool)
    if ce:
        slip = launch & (w < f.we_min)
        we = np.where(slip, f.we_min, w)
        k = np.where(slip, f.we_min / np.where(w > 0, w, 1.0), 1.0)
        ok &= (we >= f.we_min * (1 - 1e-9)) & (we <= f.we_max) & (w > 0)
        t_lo, t_hi = _engine_limits(f, we)
        pe_hi = t_hi / k
        pe_lo = np.where(slip, 0.0, t_lo / k)
        pe0 = _engine_friction(f, we)
    else:
        k, pe_lo, pe_hi, pe0 = np.ones(w.shape), zero, zero, zero
    if cm:
        ok &= w <= f.wm_max
        m_lim = np.minimum(f.tm_max * w, f.pm_max)
        pm0 = _motor_friction(f, w)
    else:
        m_lim, pm0 = zero, zero
    return ok, cm, ce, k, pe_lo, pe_hi, pe0, m_lim, pm0


def _ranges(f, mode: int, P_d, w, launch) -> _Ranges:
    """Ranges of `mode` (index) at demand P_d (W) and gearbox speed w (rad/s), written from
    eqs. 1-7, 10-12: what the mode can do (`_caps`); the motor (or nothing) covers P_d minus at
    most the engine's full load, service brakes take any surplus."""
    P_d, w, launch = np.broadcast_arrays(np.asarray(P_d, float), np.asarray(w, float), launch)
    ok, cm, ce, k, pe_lo, pe_hi, pe0, m_lim, pm0 = _caps(f, mode, w, launch)
    zero = np.zeros(P_d.shape)
    pm_lo = np.maximum(-m_lim, P_d - pe_hi)
    ok &= pm_lo <= m_lim
    if cm:
        pb_lo, pb_hi = _pb_of_pm(f, pm0, pm_lo), _pb_of_pm(f, pm0, m_lim)
    else:
        pb_lo, pb_hi = zero, zero
    idle = -_engine_friction(f, f.we_min) / f.eta_e if f.has_motor < 0.5 else 0.0
    return _Ranges(ok, cm, ce, k, pe_lo, pe_hi, pe0, pm0, pb_lo, pb_hi, idle)


def _evaluate(f, r: _Ranges, P_d, lam, P_b):
    """H, P_f, P_m at battery powers P_b (broadcast against r's shape + trailing axes)."""
    if r.cm:
        P_m = _pm_of_pb(f, r.pm0, P_b)
    else:
        P_m = np.zeros(np.shape(P_b))
    if r.ce:
        out = np.clip(P_d - P_m, r.pe_lo, r.pe_hi)  # the brakes take what the engine cannot
        P_f = np.maximum(r.k * out - r.pe0, 0.0) / f.eta_e
    else:
        P_f = np.full(np.shape(P_m), r.idle)
    return P_f - lam * (P_b + f.beta * P_b * P_b), P_f, P_m


def ref_split(vp: VehicleParams, P_d, v, lam, n: int = 100_001):
    """Brute force: for every (mode, gear) the minimum of H over a P_b grid of n points spanning
    exactly the feasible interval (one time step; P_d W, v m/s, lam scalars).

    Returns (H, P_b, spacing), each (4, n_gears): +inf / 0 / 0 where infeasible; spacing is the
    grid step (0 for modes without the motor, whose P_b is 0).
    """
    f = _veh(vp)
    w = f.gear_ratio * f.r_d * v
    launch = np.arange(w.shape[0]) == 0
    G = w.shape[0]
    H, Pb, spacing = np.full((4, G), np.inf), np.zeros((4, G)), np.zeros((4, G))
    for mode in range(N_MODES):
        r = _ranges(f, mode, P_d, w, launch)
        if r.cm:
            grid = np.linspace(r.pb_lo, r.pb_hi, n, axis=-1)  # (G, n)
        else:
            grid = np.zeros((G, 1))
        Hg, _, _ = _evaluate(f, r._replace(**{k: getattr(r, k)[:, None] for k in (
            "k", "pe_lo", "pe_hi", "pe0", "pm0")}), P_d, lam, grid)
        i = np.argmin(Hg, axis=-1)
        rows = np.arange(G)
        H[mode] = np.where(r.ok, Hg[rows, i], np.inf)
        Pb[mode] = np.where(r.ok, grid[rows, i], 0.0)
        if r.cm:
            spacing[mode] = np.where(r.ok, grid[:, 1] - grid[:, 0], 0.0)
    return H, Pb, spacing


class RefSplit(NamedTuple):
    """The optimal split of every (mode, gear) per step: arrays (T, 4, n_gears) (or the shape
    the inputs broadcast to, with the mode axis where noted). H: W, +inf where infeasible;
    P_b, P_f, P_m: W (0 where infeasible); feasible: bool."""

    H: np.ndarray
    P_b: np.ndarray
    P_f: np.ndarray
    P_m: np.ndarray
    feasible: np.ndarray


def _refined_min(f, r: _Ranges, P_d, lam, n_grid, levels):
    """Minimise H over [pb_lo, pb_hi] by a grid refined around its minimum (H convex)."""
    ex = lambda a: np.asarray(a)[..., None]  # noqa: E731
    rr = r._replace(**{k: ex(getattr(r, k)) for k in ("k", "pe_lo", "pe_hi", "pe0", "pm0")})
    P_d_, lam_ = ex(P_d), ex(lam)
    lo = np.where(r.ok, r.pb_lo, 0.0)
    hi = np.where(r.ok, r.pb_hi, 0.0)
    # the exact points first: interval ends and P_b = 0 (engine-only / open-like splits)
    pts = np.stack([lo, hi, np.clip(0.0, lo, hi)], axis=-1)
    h = _evaluate(f, rr, P_d_, lam_, pts)[0]
    i = np.argmin(h, axis=-1)[..., None]
    best_x = np.take_along_axis(pts, i, -1)[..., 0]
    best_h = np.take_along_axis(h, i, -1)[..., 0]
    a, b = lo, hi
    u = np.linspace(0.0, 1.0, n_grid)
    for _ in range(levels):
        x = a[..., None] + (b - a)[..., None] * u
        x[..., -1] = b
        h = _evaluate(f, rr, P_d_, lam_, x)[0]
        i = np.argmin(h, axis=-1)
        hx = np.take_along_axis(h, i[..., None], -1)[..., 0]
        better = hx < best_h
        best_h = np.where(better, hx, best_h)
        best_x = np.where(better, np.take_along_axis(x, i[..., None], -1)[..., 0], best_x)
        # convexity: the minimum lies between the grid neighbours of the grid's minimum
        a = np.take_along_axis(x, np.maximum(i - 1, 0)[..., None], -1)[..., 0]
        b = np.take_along_axis(x, np.minimum(i + 1, n_grid - 1)[..., None], -1)[..., 0]
    return best_x


def _solve_mode(f, r: _Ranges, P_d, lam, n_grid, levels):
    """(H, P_b, P_f, P_m) of one mode at its optimum; +inf / 0 where infeasible."""
    if r.cm:
        P_b = _refined_min(f, r, P_d, lam, n_grid, levels)
    else:
        P_b = np.zeros(r.ok.shape)
    H, P_f, P_m = _evaluate(f, r, P_d, lam, P_b)
    z = lambda a: np.where(r.ok, a, 0.0)  # noqa: E731
    return np.where(r.ok, H, np.inf), z(P_b), z(P_f), z(P_m)


def split_table(vp: VehicleParams, P_d, v, lam, n_grid: int = 33, levels: int = 12) -> RefSplit:
    """The optimal split of every (mode, gear) per step by refined brute force (see module).

    P_d, v: (T,) W and m/s; lam: () or (T,). Returns `RefSplit` of shape (T, 4, n_gears).
    """
    f = _veh(vp)
    P_d = np.asarray(P_d, float)
    v = np.asarray(v, float)
    lam = np.broadcast_to(np.asarray(lam, float), P_d.shape)
    w = v[:, None] * (f.gear_ratio * f.r_d)[None]  # (T, G)
    launch = (np.arange(w.shape[1]) == 0)[None]
    out = [[], [], [], [], []]
    for mode in range(N_MODES):
        r = _ranges(f, mode, P_d[:, None], w, launch)
        H, P_b, P_f, P_m = _solve_mode(f, r, P_d[:, None], lam[:, None], n_grid, levels)
        for lst, a in zip(out, (H, P_b, P_f, P_m, r.ok), strict=True):
            lst.append(a)
    return RefSplit(*(np.stack(x, axis=1) for x in out))


# ----------------------------------------------------------------------- switching costs
def ref_traction_table(vp: VehicleParams, v, grade, prm: SwitchCostParams):
    """Traction-interruption cost (J) of switching into each state: (3, S), eqs. A20-A22.

    Rows: mode switch only (open for dt_M), gear switch only (dt_G), both (one event of
    max(dt_M, dt_G)). During the open driveline the truck decelerates at F_0 / m, then recovers
    at the largest driveline force of the target state; the time lost is priced at lambda_t.
    When that force cannot beat the road load, or downhill, the kinetic energy change is priced
    at lambda_k. A switch into the open mode costs nothing; a state whose engine would run below
    idle at the speed left after the event (gears above 1) costs `STRANDED_J`.
    """
    f = _veh(vp)
    v = float(v)
    F0 = float(road_load(f, v, grade))
    w = f.gear_ratio * f.r_d * v  # (G,)
    e_ok = (w >= f.we_min * (1 - 1e-9)) & (w <= f.we_max)
    pe = np.where(e_ok, np.interp(w, f.te_max_w, f.te_max) * w, 0.0)
    pm = np.where(w <= f.wm_max, _motor_limit(f, w), 0.0)
    ce = np.array(ENGINE_CONNECTED, float)[:, None]
    cm = np.array(MOTOR_CONNECTED, float)[:, None]
    F_max = (ce * pe + cm * pm) / max(v, float(prm.v_min))  # (4, G)
    m = f.mass
    lt, lk = float(prm.lambda_t), float(prm.lambda_k)
    out = np.zeros((3, N_MODES, w.shape[0]))
    for row, tau in enumerate((f.dt_M, f.dt_G, max(f.dt_M, f.dt_G))):
        v0 = max(v, float(prm.v_min))
        a0 = -F0 / m
        v1 = max(v0 + a0 * tau, 0.0)
        t_open = min(tau, v0 / max(-a0, 1e-30)) if a0 < 0 else tau
        s1 = v0 * t_open + 0.5 * a0 * t_open**2
        decel = (F0 > 0) & (F0 < F_max)
        a2 = np.where(decel, (F_max - F0) / m, 1.0)
        t_r = np.where(decel, (v0 - v1) / a2, 0.0)
        s2 = s1 + v1 * t_r + 0.5 * a2 * t_r * t_r
        dt_t = np.where(decel, s2 / v0 - (tau + t_r), 0.0)  # time lost, <= 0 (A20)
        c_kin = -lk * 0.5 * m * abs(v1 * v1 - v0 * v0)
        cost = np.where(decel, lt * dt_t, 0.0 if F0 == 0 else c_kin)
        # stranded: after the event a connected engine would run below idle (gear 1 slips)
        v_after = max(v - max(F0, 0.0) * tau / m, 0.0)
        w1 = f.gear_ratio * f.r_d * v_after
        bad = (w1 < f.we_min * (1 - 1e-9)) & (np.arange(w.shape[0]) > 0) & (v > 0)
        cost = cost + np.where((ce > 0) & bad[None], STRANDED_J, 0.0)
        cost[MO] = 0.0
        out[row] = cost
    return out.reshape(3, -1)


def ref_cost_matrix(vp: VehicleParams, v, grade, lam, prm: SwitchCostParams, extra=None):
    """Switching cost eps_M + eps_G (J) between all states at one step: (S, S), [s, s'] for
    s -> s'. Per component c (engine, motor) the rotational energy U_c = 1/2 I_c x_c w^2 (x_c
    connected, w the gearbox input speed of the gear); the synchronisation energy is
    (1 - a) max(U_c' - U_c, 0) + a |U_c' - U_c| / 2 summed over c (a = `averaged`), priced at
    -lambda_b (A17-A19), plus the traction cost of the switch's kind into s' (and `extra`
    (3, S), Level 1's braking loss `ref_braking_loss`); 0 on the diagonal.
    """
    f = _veh(vp)
    n_g = f.gear_ratio.shape[0]
    S = N_MODES * n_g
    w = f.gear_ratio * f.r_d * float(v)
    trac = ref_traction_table(vp, v, grade, prm)
    trac = trac if extra is None else trac + np.asarray(extra, float)
    a = float(prm.averaged)
    mode, gear = np.arange(S) // n_g, np.arange(S) % n_g
    E = np.zeros((S, S))
    for inertia, flags in ((f.I_e, ENGINE_CONNECTED), (f.I_m, MOTOR_CONNECTED)):
        U = 0.5 * inertia * np.asarray(flags, float)[mode] * w[gear] ** 2  # (S,)
        dU = U[None, :] - U[:, None]  # [s, s'] = U(s') - U(s)
        E += (1 - a) * np.maximum(dU, 0.0) + a * 0.5 * np.abs(dU)
    dm = mode[:, None] != mode[None, :]
    dg = gear[:, None] != gear[None, :]
    row = np.where(dm & dg, 2, np.where(dm, 0, 1))
    C = float(prm.weight) * (-float(lam) * E + trac[row, np.arange(S)[None, :]])
    C[~(dm | dg)] = 0.0
    return C


# ------------------------------------------------------------------------------- Viterbi
class RefViterbi(NamedTuple):
    """path: (T,) optimal states; start: the state before step 0; cost: optimal J (+inf if
    no finite path)."""

    path: np.ndarray
    start: int
    cost: float


def viterbi_path(stage, Cs, init, mask=None) -> RefViterbi:
    """Plain Viterbi loop: stage (T, S) state costs (+inf forbids), Cs (T, S, S) transition
    costs [k, s, s'] or a function k -> (S, S), init (S,) cost of the state before step 0,
    mask (T,) bool or None (False: no cost, state kept).

    V_k(s') = stage_k(s') + min_s V_{k-1}(s) + C_k(s, s'); ties keep the state, then go to the
    lowest source; the path ends in the lowest state among the minima.
    """
    stage = np.asarray(stage, float)
    T, S = stage.shape
    V = np.asarray(init, float).copy()
    ident = np.arange(S)
    ptr = np.empty((T, S), np.int64)
    for k in range(T):
        if mask is not None and not mask[k]:
            ptr[k] = ident
            continue
        C = Cs(k) if callable(Cs) else Cs[k]
        tot = V[:, None] + C
        arg = np.argmin(tot, axis=0)
        best = tot[arg, ident]
        stay = V <= best
        ptr[k] = np.where(stay, ident, arg)
        V = np.where(stay, V, best) + stage[k]
    s = int(np.argmin(V))
    cost = float(V[s])
    path = np.empty(T, np.int64)
    for k in range(T - 1, -1, -1):
        path[k] = s
        s = int(ptr[k, s])
    return RefViterbi(path=path, start=s, cost=cost)


def numpy_viterbi(stage, Cs, init):
    """Plain loop: stage (T, S), Cs (T, S, S), init (S,) -> optimal cost."""
    return viterbi_path(stage, Cs, init).cost


# ------------------------------------------------------------------------------- Level 2
def _gears(f, P_d, v, w):
    """Gear per step (the rule of `battery.select_gears`) and whether any gear is feasible."""
    ws = np.asarray(v, float)[:, None] * (f.gear_ratio * f.r_d)[None]  # (T, G)
    launch = (np.arange(ws.shape[1]) == 0)[None]
    feas = np.zeros(ws.shape, bool)
    for mode in range(N_MODES):
        feas |= _ranges(f, mode, np.asarray(P_d, float)[:, None], ws, launch).ok
    d = np.abs(ws - np.asarray(w, float)[:, None])
    any_feas = feas.any(axis=1)
    gear = np.where(any_feas, np.argmin(np.where(feas, d, np.inf), axis=1), np.argmin(d, axis=1))
    return gear, any_feas


def ref_gears(vp: VehicleParams, P_d, v, w):
    """Gear index per step: among the gears in which some mode meets P_d, the one whose shaft
    speed is nearest to w (rad/s); the nearest of all where none does. P_d, v, w: (T,)."""
    return _gears(_veh(vp), P_d, v, w)[0]


class RefSteps(NamedTuple):
    """Level 2 per step at one costate: (T,) mode, P_b (W), dE = -P_bi dt (J), E_f (J)."""

    mode: np.ndarray
    P_b: np.ndarray
    dE: np.ndarray
    E_f: np.ndarray


class _Level2Model:
    """The Level 2 step model at fixed gears: the four modes' ranges, computed once."""

    def __init__(self, vp, P_d, v, gear, ok, dt, n_grid=33, levels=12):
        self.f = f = _veh(vp)
        self.P_d = np.asarray(P_d, float)
        w = np.asarray(v, float) * f.gear_ratio[gear] * f.r_d
        self.ranges = [_ranges(f, m, self.P_d, w, gear == 0) for m in range(N_MODES)]
        self.ok, self.dt = np.asarray(ok, bool), dt
        self.n_grid, self.levels = n_grid, levels

    def steps(self, lam) -> RefSteps:
        sols = [_solve_mode(self.f, r, self.P_d, lam, self.n_grid, self.levels)
                for r in self.ranges]
        H = np.stack([s[0] for s in sols])  # (4, T)
        m = np.argmin(H, axis=0)  # ties: the lowest mode index
        k = np.arange(H.shape[1])
        use = self.ok & np.isfinite(H[m, k])
        P_b = np.where(use, np.stack([s[1] for s in sols])[m, k], 0.0)
        E_f = np.where(use, np.stack([s[2] for s in sols])[m, k], 0.0) * self.dt
        dE = -(P_b + self.f.beta * P_b * P_b) * self.dt
        return RefSteps(mode=m, P_b=P_b, dE=dE, E_f=E_f)


def ref_steps(vp: VehicleParams, P_d, v, gear, ok, lam, dt, n_grid=33, levels=12) -> RefSteps:
    """Level 2 per step (eqs. 52-53) at costate lam: in the given gear, the mode with the least
    H (refined brute force over P_b); steps with ok False (no feasible gear, padding) use
    P_b = 0 and no fuel. P_d, v, gear, ok: (T,)."""
    return _Level2Model(vp, P_d, v, gear, ok, dt, n_grid, levels).steps(lam)


def ref_paths(vp: VehicleParams, P_d, v, gear, ok, lams, dt, E0) -> np.ndarray:
    """E_b (J) at the step boundaries from E0 at each constant costate of `lams`: (L, T+1),
    `ref_steps`' model built once for all of them."""
    return _paths(_Level2Model(vp, P_d, v, gear, ok, dt), lams, E0)


def _paths(model: _Level2Model, lams, E0) -> np.ndarray:
    return np.array([np.concatenate([[E0], E0 + np.cumsum(model.steps(lam).dE)])
                     for lam in np.atleast_1d(lams)])


def ref_end(vp: VehicleParams, P_d, v, w, lam, dt, E0, mask=None):
    """E_b(t_f) (J) at a constant lambda_b: gears by `ref_gears`, then the best mode of each
    step at its gear, E_b(k+1) = E_b(k) - P_bi dt from E0."""
    f = _veh(vp)
    gear, any_feas = _gears(f, P_d, v, w)
    ok = any_feas if mask is None else any_feas & np.asarray(mask, bool)
    return E0 + float(np.sum(ref_steps(vp, P_d, v, gear, ok, lam, dt).dE))


class RefCostate(NamedTuple):
    """Bisection on one constant lambda_b: lam = (lam_lo + lam_hi) / 2; E_end_lo, E_end_hi:
    E_b(t_f) at the final bracket (they differ by a jump at a guard); gear, ok: (T,) Level 2's
    gears and usable steps; steps: `RefSteps` at lam."""

    lam: float
    lam_lo: float
    lam_hi: float
    E_end_lo: float
    E_end_hi: float
    gear: np.ndarray
    ok: np.ndarray
    steps: RefSteps


def ref_bisect(vp: VehicleParams, P_d, v, w, mask=None, dt=1.0, E_b0=None, E_b_end=None,
               lam_bracket=LAM_BRACKET, n_iter: int = 40, n_grid: int = 33,
               levels: int = 12) -> RefCostate:
    """Level 2 without battery limits: bisection on a constant lambda_b so that E_b(t_f) =
    E_b_end (default E_b0 = soc0 E_b_max: charge sustaining). E_b(t_f) does not increase with
    lambda_b, so lambda_b rises while E_b(t_f) ends above the target; `n_iter` halvings of
    `lam_bracket`, as `battery.bisect_costate` does."""
    f = _veh(vp)
    E0 = f.soc0 * f.E_b_max if E_b0 is None else float(E_b0)
    tgt = E0 if E_b_end is None else float(E_b_end)
    gear, any_feas = _gears(f, P_d, v, w)
    ok = any_feas if mask is None else any_feas & np.asarray(mask, bool)
    model = _Level2Model(vp, P_d, v, gear, ok, dt, n_grid, levels)
    lo, hi = (float(x) for x in lam_bracket)
    e_lo = E0 + float(np.sum(model.steps(lo).dE))
    e_hi = E0 + float(np.sum(model.steps(hi).dE))
    for _ in range(n_iter):
        mid = 0.5 * (lo + hi)
        e = E0 + float(np.sum(model.steps(mid).dE))
        if e > tgt:
            lo, e_lo = mid, e
        else:
            hi, e_hi = mid, e
    lam = 0.5 * (lo + hi)
    return RefCostate(lam=lam, lam_lo=lo, lam_hi=hi, E_end_lo=e_lo, E_end_hi=e_hi, gear=gear,
                      ok=ok, steps=model.steps(lam))


class RefHorizon(NamedTuple):
    """I3's window without an end value: lam_lo, lam_hi the final bracket; E_mix (T+1,) the
    two sides' paths mixed at fraction r on B+ (I2a); margin its smallest distance to the
    limits (J, negative: crossed); event: no costate keeps the path within the limits (I3a);
    t_event: the boundary of its largest violation (T where there is none, as the kernel
    gives it; `event` tells the two apart); limit: the limit crossed there (J)."""

    lam_lo: float
    lam_hi: float
    r: float
    E_mix: np.ndarray
    margin: float
    event: bool
    t_event: int
    limit: float


def ref_horizon(vp: VehicleParams, P_d, v, gear, ok, dt, E_b0, E_min, E_max, tol,
                lam_bracket=LAM_BRACKET, n_iter: int = 40, n_mix: int = 50) -> RefHorizon:
    """I3 (section 5.3) as loops: the costate that maximises the smaller of the distances of
    E_b to E_min and to E_max (d_low falls and d_up rises with lambda_b: bisection on which
    is larger, `n_iter` halvings), then the paths of the bracket's ends mixed (I2a, `n_mix`
    halvings of the fraction) to balance the two; the mix's largest violation is an event
    (I3a) where it exceeds tol (J), after the start. Gears given, as `ref_steps` takes
    them."""
    model = _Level2Model(vp, P_d, v, gear, ok, dt)

    def path(lam):
        return _paths(model, lam, E_b0)[0]

    def dists(E):
        return E.min() - E_min, E_max - E.max()

    lo, hi = (float(x) for x in lam_bracket)
    for _ in range(n_iter):
        mid = 0.5 * (lo + hi)
        d_low, d_up = dists(path(mid))
        lo, hi = (mid, hi) if d_low > d_up else (lo, mid)
    E_plus, E_minus = path(lo), path(hi)
    ra, rb = 0.0, 1.0
    for _ in range(n_mix):
        r = 0.5 * (ra + rb)
        d_low, d_up = dists(E_minus + r * (E_plus - E_minus))
        ra, rb = (r, rb) if d_low < d_up else (ra, r)
    r = 0.5 * (ra + rb)
    E_mix = E_minus + r * (E_plus - E_minus)
    margin = min(dists(E_mix))
    viol = np.maximum(np.maximum(E_mix - E_max, E_min - E_mix), 0.0)
    tc = int(np.argmax(viol))
    event = margin < -tol and tc > 0
    return RefHorizon(lam_lo=lo, lam_hi=hi, r=r, E_mix=E_mix, margin=float(margin),
                      event=event, t_event=tc if event else len(E_mix) - 1,
                      limit=E_max if E_mix[tc] > E_max else E_min)


def ref_fuel_power(vp: VehicleParams, P_d, w, gear, P_b):
    """Fuel power (W) of the best mode for battery power P_b (array) at gear speed w: NumPy.

    Written from eqs. 1-7 and the mode definitions (engine and/or motor on the shaft, service
    brakes absorb a surplus, slipping clutch below idle in gear 1); +inf where infeasible.
    """
    f = _veh(vp)
    eta_e = f.eta_e
    slip = gear == 0 and w < f.we_min
    we = f.we_min if slip else w
    kf = f.we_min / w if slip else 1.0
    pe_min, pe_max = (float(x) for x in _engine_limits(f, we))
    e_ok = f.we_min * (1 - 1e-9) <= we <= f.we_max and w > 0
    e_lo, e_hi = pe_min / kf, pe_max / kf
    pe0 = float(_engine_friction(f, we))
    m_lim = float(_motor_limit(f, w))
    pm0 = float(_motor_friction(f, w))
    m_ok = w <= f.wm_max
    P_b = np.asarray(P_b, float)
    P_m = _pm_of_pb(f, pm0, P_b)
    out = np.full(P_b.shape, np.inf)

    def engine_fuel(P_out):
        return np.maximum(kf * P_out - pe0, 0.0) / eta_e

    tiny = 1e-6
    if e_ok and m_ok:  # combined
        ok = (np.abs(P_m) <= m_lim + tiny) & (P_d - P_m <= e_hi + tiny)
        out = np.where(ok, np.minimum(out, engine_fuel(np.clip(P_d - P_m, e_lo, e_hi))), out)
    zero = np.abs(P_b) < 1e-9
    if e_ok and P_d <= e_hi:  # engine-only: P_b = 0
        out = np.where(zero, np.minimum(out, engine_fuel(np.clip(P_d, e_lo, e_hi))), out)
    if m_ok:  # motor-only: P_m in [max(-m_lim, P_d), m_lim], no fuel
        ok = (P_m >= max(-m_lim, P_d) - tiny) & (P_m <= m_lim + tiny)
        out = np.where(ok, np.minimum(out, 0.0), out)
    if P_d <= 0:  # open driveline
        out = np.where(zero, 0.0, out)
    return out


def _lower_envelope(x, y):
    """The lower convex envelope of the points (x, y) (1-D arrays), evaluated at each x."""
    order = np.lexsort((y, x))
    hull: list[tuple[float, float]] = []
    for p in zip(x[order].tolist(), y[order].tolist(), strict=True):
        if hull and hull[-1][0] == p[0]:  # the lowest of equal x came first
            continue
        while len(hull) >= 2 and ((hull[-1][0] - hull[-2][0]) * (p[1] - hull[-2][1])
                                  <= (hull[-1][1] - hull[-2][1]) * (p[0] - hull[-2][0])):
            hull.pop()
        hull.append(p)
    hx, hy = np.array(hull).T
    return np.minimum(y, np.interp(x, hx, hy))


def ref_dp(vp: VehicleParams, P_d, v, w, dt, E0, E_min, E_max, n_grid, n_ctrl=301,
           end_weight=6.0, shared=False):
    """Minimal fuel (J) by DP over an E_b grid of n_grid points with E_b(t_f) = E0.

    Backward recursion with the cost-to-go interpolated linearly between grid points. Controls
    per step: n_ctrl battery powers over the motor's range plus the exact points of the
    engine-only / open (P_b = 0) and motor-only (P_m = P_d) modes; the fuel of the best mode
    for each. The end condition is a penalty end_weight |E_b - E0| with end_weight above every
    costate in the bracket, so missing it never pays.

    shared: a step may share its time between two of its controls (what Level 2's mix of its
    B+ and B- trajectories does, eq. 55 and I2b), so each step's fuel over its change of E_b
    is replaced by its lower convex envelope: a relaxation of the one-control-a-step DP, whose
    optimum no schedule of Level 2's beats (but for the grid's error).
    """
    f = _veh(vp)
    gears = ref_gears(vp, P_d, v, w)
    grid = np.linspace(E_min, E_max, n_grid)
    beta, eta_m = f.beta, f.eta_m
    big = 1e15
    V = end_weight * np.abs(grid - E0)
    for k in range(len(P_d) - 1, -1, -1):
        wk = float(f.gear_ratio[gears[k]] * f.r_d * v[k])
        m_lim = float(_motor_limit(f, wk))
        pm0 = float(_motor_friction(f, wk))
        lim_b = (m_lim - pm0) / eta_m + 1.0
        d = P_d[k] - pm0
        exact = d / eta_m if d > 0 else d * eta_m  # motor-only with P_m = P_d
        U = np.concatenate([np.linspace(-lim_b, lim_b, n_ctrl), [0.0, exact]])
        c = ref_fuel_power(vp, P_d[k], wk, gears[k], U) * dt
        if not np.isfinite(c).any():  # nothing feasible: the Level 2 model skips the step
            c = np.where(U == 0.0, 0.0, np.inf)
        keep = np.isfinite(c)
        U, c = U[keep], c[keep]
        dE = -(U + beta * U * U) * dt
        if shared:
            c = _lower_envelope(dE, c)
        E_next = grid[:, None] + dE[None, :]
        inside = (E_next >= E_min - 1e-9) & (E_next <= E_max + 1e-9)
        Vn = np.interp(E_next, grid, V)
        V = np.min(np.where(inside, c[None, :] + Vn, big), axis=1)
    return float(np.interp(E0, grid, V))


def ref_minimal_switching(dE_plus, dE_minus, E_b0, E_b_end, E_min, E_max, tol=1e-9):
    """I2b by brute force: the fewest switches between the B+ and B- trajectories.

    The problem `battery.minimal_switching` solves: each step runs on one side, except a
    switching step, whose fraction sel_k in [0, 1] on B+ is free (the switch falls inside the
    step); E_b at the step boundaries within [E_min, E_max] (the last one on E_b_end), all
    within tol. Every set of switching steps, fewest first, from either side, is a linear
    feasibility problem in its fractions (scipy's HiGHS). Returns (feasible, fewest switches,
    None where infeasible). Exponential in T: for small tests."""
    from itertools import combinations

    from scipy.optimize import linprog

    dp, dm = np.asarray(dE_plus, float), np.asarray(dE_minus, float)
    T = dp.shape[0]
    delta = dp - dm
    base = E_b0 + np.cumsum(dm)  # E_b after each step on B-
    lo = np.full(T, E_min - tol)
    hi = np.full(T, E_max + tol)
    lo[-1], hi[-1] = E_b_end - tol, E_b_end + tol
    below = np.tril(np.ones((T, T)))  # [j, k]: step k comes before the boundary after step j

    def feasible(free, fixed):  # free: steps with a free fraction; fixed: (T,) the others'
        c0 = base + below @ (fixed * delta)
        if not free:
            return bool(np.all((c0 >= lo) & (c0 <= hi)))
        A = below[:, free] * delta[free][None, :]
        res = linprog(np.zeros(len(free)), A_ub=np.vstack([A, -A]),
                      b_ub=np.concatenate([hi - c0, c0 - lo]), bounds=[(0.0, 1.0)] * len(free),
                      method="highs")
        return res.status == 0

    if not feasible(list(range(T)), np.zeros(T)):
        return False, None
    for n in range(T + 1):
        for side0 in (0.0, 1.0):
            for steps in combinations(range(T), n):
                side = np.full(T, side0)
                for k in steps:  # the side flips within step k
                    side[k + 1:] = 1.0 - side[k + 1:]
                if feasible(list(steps), np.where(np.isin(np.arange(T), steps), 0.0, side)):
                    return True, n
    return True, None  # not reached: T free steps include the all-free problem


# ---------------------------------------------------------------------------- the pipeline
class RefPlan(NamedTuple):
    """`reference_plan`'s result. mode, gear, state: (T,) the Level 1 plan (indices); P_b, P_f:
    (T,) W of the planned split (0 on masked or infeasible steps); fuel_J: () sum of P_f dt;
    cost: () the DP's optimum (J: H dt + switching costs); lam: () Level 2's costate;
    n_infeasible: () steps without a feasible (mode, gear); pred: `RefPrediction`; costate:
    `RefCostate`; stage_s: wall seconds per stage (level3, level2, level1_table, viterbi)."""

    mode: np.ndarray
    gear: np.ndarray
    state: np.ndarray
    P_b: np.ndarray
    P_f: np.ndarray
    fuel_J: float
    cost: float
    lam: float
    n_infeasible: int
    pred: RefPrediction
    costate: RefCostate
    stage_s: dict


def ref_level1(vp: VehicleParams, P_d, v, grade, lam, dt, params: SwitchCostParams, init,
               mask, n_grid: int = 33, levels: int = 12, stage_s: dict | None = None,
               first: int | None = None):
    """Level 1 over T steps: `split_table` at the costate (H dt per state, 0 for every state of
    a step where none is feasible) and `viterbi_path` with `ref_cost_matrix` of each step
    (speed, gradient, costate; the recuperation a switch loses braking, `ref_braking_loss`) as
    transition costs, from init (S,) (the cost of each state before step 0); steps outside mask
    keep the state; first, where given, the only state allowed at step 0 (the best path that
    starts with that decision). P_d, v, grade, mask: (T,); lam: () or (T,). Returns
    (`RefViterbi`, `RefSplit` (T, 4, n_gears)); stage_s, where given, gets the wall
    seconds of the table ("level1_table") and of the DP ("viterbi")."""
    t0 = time.perf_counter()
    P_d, v, grade = (np.asarray(a, float) for a in (P_d, v, grade))
    T = P_d.shape[0]
    lam = np.broadcast_to(np.asarray(lam, float), (T,))
    tab = split_table(vp, P_d, v, lam, n_grid, levels)
    H = tab.H.reshape(T, -1) * dt
    H[~np.any(np.isfinite(H), axis=1)] = 0.0
    if first is not None:
        H[0, np.arange(H.shape[1]) != first] = np.inf
    t1 = time.perf_counter()
    brake = ref_braking_loss(vp, tab.H, P_d, dt)

    def costs(k):
        return ref_cost_matrix(vp, v[k], grade[k], lam[k], params, brake[k])

    vit = viterbi_path(H, costs, init, np.asarray(mask, bool))
    if stage_s is not None:
        stage_s.update(level1_table=t1 - t0, viterbi=time.perf_counter() - t1)
    return vit, tab


def reference_plan(route: Route, vp: VehicleParams, dt: float = 1.0, n_iter_l2: int = 40,
                   n_steps: int | None = None, params: SwitchCostParams | None = None,
                   n_grid: int = 33, levels: int = 12) -> RefPlan:
    """Iteration 0 of the multilevel planning pipeline in NumPy (one route, one vehicle).

    1. Level 3: `ref_prediction` (engine speed w_pred in the forward pass), n_steps steps of dt.
    2. Level 2: `ref_bisect` with n_iter_l2 halvings: charge sustaining from soc0 E_b_max, no
       battery limits, gears from the constant engine speed w_pred.
    3. Level 1: `split_table` at Level 2's costate (H dt per state, 0 for every state of a step
       where none is feasible) and `viterbi_path` with `ref_cost_matrix` of each step (speed,
       gradient, costate; the recuperation a switch loses braking, `ref_braking_loss`) as
       transition costs; from the open driveline in gear 1 when the
       route starts at standstill, free otherwise; masked steps keep the state.

    n_grid, levels: the refined brute-force search of the Level 1 and Level 2 splits.
    Returns `RefPlan`.
    """
    params = SwitchCostParams() if params is None else params
    f = _veh(vp)
    stage_s = {}
    t0 = time.perf_counter()
    pred = ref_prediction(route, vp, dt, n_steps)
    t1 = time.perf_counter()
    stage_s["level3"] = t1 - t0
    T = pred.v.shape[0]
    w = np.full(T, f.w_pred)
    c2 = ref_bisect(vp, pred.P_d, pred.v, w, pred.mask, dt, n_iter=n_iter_l2, n_grid=n_grid,
                    levels=levels)
    t2 = time.perf_counter()
    stage_s["level2"] = t2 - t1
    lam = c2.lam
    S = N_MODES * f.gear_ratio.shape[0]
    n_g = S // N_MODES
    init = np.zeros(S)
    if pred.v_ref[0] <= 0:
        init = np.full(S, np.inf)
        init[MO * n_g] = 0.0
    vit, tab = ref_level1(vp, pred.P_d, pred.v, pred.grade, lam, dt, params, init, pred.mask,
                          n_grid, levels, stage_s)
    none = ~np.any(np.isfinite(tab.H.reshape(T, -1)), axis=1)
    path = vit.path
    mode, gear = path // n_g, path % n_g
    k = np.arange(T)
    P_b = np.where(pred.mask, tab.P_b[k, mode, gear], 0.0)
    P_f = np.where(pred.mask, tab.P_f[k, mode, gear], 0.0)
    return RefPlan(
        mode=mode, gear=gear, state=path, P_b=P_b, P_f=P_f, fuel_J=float(np.sum(P_f) * dt),
        cost=vit.cost, lam=lam, n_infeasible=int(np.sum(pred.mask & none)), pred=pred,
        costate=c2, stage_s=stage_s,
    )


# ------------------------------------------------------------- the same stages through JAX
class KernelPlan(NamedTuple):
    """`kernel_plan`'s result (arrays): mode, gear, P_b (W), P_f (W): (T,) the plan; fuel_J,
    cost, lam: (); status: () Level 2's status flags (`battery.status_names`); P_d (W), v
    (m/s), grade, mask: (T,) the Level 3 prediction the plan is for."""

    mode: Any
    gear: Any
    P_b: Any
    P_f: Any
    fuel_J: Any
    cost: Any
    lam: Any
    status: Any
    P_d: Any
    v: Any
    grade: Any
    mask: Any


def kernel_level3(route: Route, vp: VehicleParams, *, dt: float, n_steps: int):
    """Stage 1 of `kernel_plan`: the Level 3 `Prediction` (`strategies.level3`, w_pred)."""
    from . import strategies

    return strategies.level3(route, vp, dt, n_steps)


def kernel_level2(vp: VehicleParams, pred, *, dt: float, n_iter_l2: int = 40):
    """Stage 2 of `kernel_plan`: `battery.costate_kernel` with one piece and no battery limits
    (plain bisection on lambda_b, charge sustaining), gears from the constant engine speed
    w_pred. Returns its `CostateResult`."""
    import jax.numpy as jnp

    from .levels import battery as l2

    w = jnp.full_like(pred.v, vp.w_pred)
    return l2.costate_kernel(vp, pred.P_d, pred.v, w, pred.mask, dt, E_min=-jnp.inf,
                             E_max=jnp.inf, n_iter=n_iter_l2, max_pieces=1)


def kernel_level1(vp: VehicleParams, pred, lam, params: SwitchCostParams, *, dt: float):
    """Stage 3 of `kernel_plan`: `plan.level1` (Hamiltonian table, switching costs,
    Viterbi; the start state of the strategy) at the costate lam. Returns `Level1Result`."""
    from . import plan

    return plan.level1(vp, pred, lam, dt, params)


def kernel_plan(route: Route, vp: VehicleParams, params: SwitchCostParams, *, dt: float,
                n_steps: int, n_iter_l2: int = 40) -> KernelPlan:
    """The stages of `reference_plan` through the JAX kernels (traceable; jit and vmap it):
    `kernel_level3`, `kernel_level2` and `kernel_level1` at Level 2's first costate. dt,
    n_steps, n_iter_l2 are static."""
    import jax.numpy as jnp

    pred = kernel_level3(route, vp, dt=dt, n_steps=n_steps)
    c2 = kernel_level2(vp, pred, dt=dt, n_iter_l2=n_iter_l2)
    r1 = kernel_level1(vp, pred, c2.lam0, params, dt=dt)
    fuel = jnp.sum(jnp.where(pred.mask, r1.P_f, 0.0)) * dt
    return KernelPlan(mode=r1.mode, gear=r1.gear, P_b=r1.P_b, P_f=r1.P_f, fuel_J=fuel,
                      cost=r1.cost, lam=c2.lam0, status=c2.status, P_d=pred.P_d, v=pred.v,
                      grade=pred.grade, mask=pred.mask)


def compare_plans(ref: RefPlan, ker: KernelPlan) -> dict:
    """Agreement of a kernel plan with the reference: relative fuel difference, costate
    difference, and the fraction of valid steps with the same mode, gear, and both."""
    m = ref.pred.mask
    mode = np.asarray(ker.mode)[m] == ref.mode[m]
    gear = np.asarray(ker.gear)[m] == ref.gear[m]
    fuel = float(ker.fuel_J)
    return {
        "fuel_rel": abs(fuel - ref.fuel_J) / max(abs(ref.fuel_J), 1.0),
        "lam_abs": abs(float(ker.lam) - ref.lam),
        "mode_agree": float(np.mean(mode)),
        "gear_agree": float(np.mean(gear)),
        "state_agree": float(np.mean(mode & gear)),
    }


__all__ = [
    "KernelPlan", "RefCostate", "RefPlan", "RefPrediction", "RefSplit", "RefSteps", "RefViterbi",
    "a_fwd", "compare_plans", "kernel_level1", "kernel_level2", "kernel_level3", "kernel_plan",
    "numpy_viterbi", "ref_bisect", "ref_cost_matrix", "ref_dp", "ref_end", "ref_fuel_power",
    "ref_gears", "ref_pieces", "ref_prediction", "ref_profile", "ref_split", "ref_steps",
    "ref_minimal_switching", "ref_time_grid", "ref_traction_table", "reference_plan",
    "road_load", "split_table", "viterbi_path",
]


# ------------------------------------------------------------------ eco-driving (Level 3 DP)
def ref_hamiltonian_min(vp: VehicleParams, P_d, v, lam, n_grid: int = 9, levels: int = 14):
    """Hard minimum over modes and gears of H (W) by `split_table`'s brute force, for arrays
    P_d, v of one shape; where nothing can deliver P_d: P_PENALTY_W + 2 max(P_d, 0) / eta_e
    (the convention of `velocity.soft_min_hamiltonian`)."""
    f = _veh(vp)
    P_d = np.asarray(P_d, float)
    v = np.asarray(v, float)
    flat_P, flat_v = P_d.ravel(), v.ravel()
    H = np.empty(flat_P.shape)
    for a in range(0, flat_P.size, 8192):
        tab = split_table(vp, flat_P[a:a + 8192], flat_v[a:a + 8192], lam, n_grid, levels).H
        H[a:a + 8192] = tab.reshape(tab.shape[0], -1).min(axis=1)
    H = H.reshape(P_d.shape)
    return np.where(np.isfinite(H), H, P_PENALTY_W + 2.0 * np.maximum(P_d, 0.0) / f.eta_e)


def ref_eco_cell(vp: VehicleParams, v0, v1, grade, ds):
    """The eco-driving cell model in NumPy: (P_d W, v_mean m/s, dt s) of cells driven from
    speed v0 to v1 (arrays) at constant acceleration over ds metres: dt = 2 ds / (v0 + v1)
    (the sum floored at V_CRAWL), P_d = (kinetic energy change + road-load work) / dt with
    F_0 = k_air v^2 + m g (c_r cos alpha + sin alpha) and v^2 linear in s, v_mean = ds / dt."""
    f = vp if isinstance(vp, SimpleNamespace) else _veh(vp)
    vsum = np.maximum(v0 + v1, V_CRAWL)
    dt = 2.0 * ds / vsum
    k_air = 0.5 * f.c_w * f.area * f.rho
    work = (k_air * 0.5 * (v0 * v0 + v1 * v1) + road_load(f, 0.0, grade)) * ds
    P_d = (0.5 * f.mass * (v1 * v1 - v0 * v0) + work) / dt
    return P_d, 0.5 * vsum, dt


class RefEco(NamedTuple):
    """`ref_eco_dp`'s optimum: v: (n,) node speeds (m/s); cost: J (energy + lambda_t x trip
    time, stops included); energy: J (sum H dt); trip_time: s; envelope: (n,) Level 3's
    speeds (the upper bound)."""

    v: np.ndarray
    cost: float
    energy: float
    trip_time: float
    envelope: np.ndarray


def ref_eco_dp(route: Route, vp: VehicleParams, lambda_t, lam_b, v_grid, h_min=None, w=None,
               acc_tol: float = 1e-9) -> RefEco:
    """Eco-driving by dynamic programming over nodes x speeds (the reference of
    `velocity.optimize_velocity`).

    At node i the speed is one of the grid speeds v_grid (m/s) inside [floor_i, env_i], or
    env_i itself: env is Level 3's profile (`ref_profile`), floor 0 at stops and
    min(V_CRAWL, env) elsewhere; the first and last node are fixed to env. A transition
    (cell i, speed a -> b) is allowed when -a_min - acc_tol <= (b^2 - a^2) / (2 ds) <=
    a_fwd(a, grade_i, w_i) + acc_tol and costs (H + lambda_t) dt from `ref_eco_cell`, H the
    hard minimum over modes and gears at (P_d, v_mean): `h_min(P_d, v_mean)` (arrays in,
    array out; default `ref_hamiltonian_min` at lam_b). Forward cost-to-come with a loop over
    cells, vectorised over (from, to) speed pairs; back-pointers give the path.
    """
    f = _veh(vp)
    if h_min is None:
        h_min = lambda P, v: ref_hamiltonian_min(vp, P, v, lam_b)  # noqa: E731
    n = n_nodes(route)
    ds = float(route.ds)
    g = np.asarray(route.grade, float)[:n]
    stop = np.asarray(route.stop, float)[:n]
    ww = np.full(n, f.w_pred) if w is None else np.broadcast_to(np.asarray(w, float), (n,))
    env, _, _, _ = ref_profile(route, vp, w)
    floor = np.where(stop > 0, 0.0, np.minimum(V_CRAWL, env))
    grid = np.asarray(v_grid, float)
    cand = []
    for i in range(n):
        if i in (0, n - 1) or stop[i] > 0:
            c = np.array([env[i]])
        else:
            inside = grid[(grid >= floor[i]) & (grid < env[i])]
            c = np.unique(np.concatenate([inside, [env[i]]]))
        cand.append(c)
    J = np.zeros(1)
    back = []
    for i in range(n - 1):
        a, b = cand[i][:, None], cand[i + 1][None, :]
        acc = (b * b - a * a) / (2.0 * ds)
        ok = (acc <= a_fwd(f, a, g[i], ww[i]) + acc_tol) & (acc >= -f.a_min - acc_tol)
        P_d, v_mean, dt = ref_eco_cell(f, a, b, g[i], ds)
        P_d, v_mean, dt = np.broadcast_arrays(P_d, v_mean, dt)
        cost = np.full(ok.shape, np.inf)
        if ok.any():
            H = h_min(P_d[ok], v_mean[ok])
            cost[ok] = (np.asarray(H) + lambda_t) * dt[ok]
        tot = J[:, None] + cost
        k = np.argmin(tot, axis=0)
        J = tot[k, np.arange(tot.shape[1])]
        back.append(k)
    if not np.isfinite(J[0]):
        raise ValueError("ref_eco_dp: no feasible path on this grid")
    idx = [0]
    for k in reversed(back):
        idx.append(int(k[idx[-1]]))
    idx = idx[::-1]
    v = np.array([cand[i][j] for i, j in enumerate(idx)])
    _, trip = ref_pieces(route, v)
    P_d, v_mean, dt = ref_eco_cell(f, v[:-1], v[1:], g[:-1], ds)
    energy = float(np.sum(np.asarray(h_min(P_d, v_mean)) * dt))
    return RefEco(v=v, cost=float(J[0]) + lambda_t * float(stop.sum()), energy=energy,
                  trip_time=float(trip), envelope=env)


__all__ += ["RefEco", "ref_eco_cell", "ref_eco_dp", "ref_hamiltonian_min"]


# ------------------------------------------------------------------------------ plans
def ref_battery_path(E0, E_max, dE, pid, target):
    """A plan's battery energy, held within [0, E_max] step by step: loop over the steps.

    dE: (T,) each step's change (J); pid: (T,) the piece of each step (non-decreasing);
    target: (K,) each piece's change. A piece starts from E0 plus the targets before it (within
    the limits). Returns (E: (T,) at each step's start, E_end: (K,) at each piece's end (its
    goal where it has no steps), goal: (K,) E0 plus the targets up to and with the piece, within
    the limits)."""
    dE, pid, target = np.asarray(dE, float), np.asarray(pid), np.asarray(target, float)
    cum = E0 + np.cumsum(target)
    goal = np.clip(cum, 0.0, E_max)
    start = np.clip(cum - target, 0.0, E_max)
    E = np.empty(dE.shape[0])
    E_end = goal.copy()
    x = E0
    for k in range(dE.shape[0]):
        if k == 0 or pid[k] != pid[k - 1]:
            x = start[pid[k]]
        E[k] = x
        x = min(max(x + dE[k], 0.0), E_max)
        E_end[pid[k]] = x
    return E, E_end, goal


def ref_plan_energy(vp: VehicleParams, P_d, v, mode, gear, P_b, dt, mask):
    """Each step's battery energy change (J) of a plan, as the plant moves it: loop over steps.

    A step whose (mode, gear) differs from the last one's (a gear change in the open mode is
    none) draws the synchronisation energy through the motor. The plant asks for the next
    step's state, so the driveline opens in the step before the new state's (dt_M at a mode
    switch, dt_G at a gear switch, the larger at both; at most the step): that step moves no
    battery power, except driving into M_m (the motor makes the lost speed up after the
    switch). Steps outside `mask` change nothing."""
    f = _veh(vp)
    P_d, v, P_b = (np.asarray(x, float) for x in (P_d, v, P_b))
    mode, gear, mask = np.asarray(mode), np.asarray(gear), np.asarray(mask)
    P_bi = P_b + float(vp.beta) * P_b * P_b  # eq. 7
    T = P_d.shape[0]
    opens = np.zeros(T)  # seconds the switch into step k's state opens the driveline
    sync = np.zeros(T)
    for k in range(1, T):
        m0, g0, m1, g1 = int(mode[k - 1]), int(gear[k - 1]), int(mode[k]), int(gear[k])
        msw = m1 != m0
        gsw = g1 != g0 and m1 != MO
        opens[k] = max(float(vp.dt_M) if msw else 0.0, float(vp.dt_G) if gsw else 0.0)
        if (msw or gsw) and float(vp.has_motor) > 0.5:
            sync[k] = _sync(f, m0, g0, m1, g1, v[k]) / f.eta_m
    out = np.zeros(T)
    for k in range(T):
        if not mask[k]:
            continue
        nxt = min(k + 1, T - 1)
        open_s = opens[k + 1] if k + 1 < T else 0.0
        driving_mm = mode[nxt] == MM and P_d[k] > 0  # M_m makes the lost speed up
        keep = 1.0 if driving_mm else 1.0 - min(open_s / dt, 1.0)
        out[k] = -P_bi[k] * dt * keep - sync[k]
    return out


def ref_braking_loss(vp: VehicleParams, H, P_d, dt):
    """(T, 3, S) J: per step, the recuperation a switch into each state loses while braking
    (P_d < 0): min(tau, dt) (H_open - H)^+ with tau = dt_M, dt_G, max(dt_M, dt_G) for a mode,
    gear or both switch, H_open the open mode's least Hamiltonian; zero driving and where H is
    infinite. Loop over steps, kinds and states. H: (T, 4, G) W; P_d: (T,) W."""
    H, P_d = np.asarray(H, float), np.asarray(P_d, float)
    T, _, G = H.shape
    taus = (float(vp.dt_M), float(vp.dt_G), max(float(vp.dt_M), float(vp.dt_G)))
    out = np.zeros((T, 3, N_MODES * G))
    for k in range(T):
        h_open = min(H[k, MO])
        if P_d[k] >= 0 or not np.isfinite(h_open):
            continue
        for m in range(N_MODES):
            for g in range(G):
                if np.isfinite(H[k, m, g]):
                    for i, tau in enumerate(taus):
                        out[k, i, m * G + g] = min(tau, dt) * max(h_open - H[k, m, g], 0.0)
    return out


__all__ += ["ref_battery_path", "ref_braking_loss", "ref_plan_energy"]


# ------------------------------------------------------------------------------ dp-bound
class RefBound(NamedTuple):
    """`ref_bound_dp`'s result: (T,) state path, candidate index, step cost (J, with the
    switching cost) and E_b at the step's start (J), E_b(tf) (J), the value's slope at
    E_b(t0) in the first state (J/J) and the value (J) at E_b(t0) before step 0 (of the start
    state; the least over states when the start is free)."""

    state: Any
    cand: Any
    cost: Any
    E: Any
    E_end: float
    lam0: float
    value: float


def _bound_interp(V1, x, dE, n_E):
    """V1 (n_E,) at E = x (J) by linear interpolation; None outside [0, (n_E - 1) dE]."""
    u = x / dE
    if u < -1e-9 or u > n_E - 1 + 1e-9:
        return None
    i0 = min(max(int(math.floor(u)), 0), n_E - 2)
    f = u - i0
    return (1 - f) * V1[i0] + f * V1[i0 + 1]


def ref_bound_dp(fuel, dEb, C, mask, s_init, E0, E_max, goal, lam_end, penalty, n_E,
                 big=1e15) -> RefBound:
    """dp-bound's DP (`bound.bound_dp`) as loops: backward over an E_b grid of n_E points
    with linear interpolation of the value function, then a forward rollout from the exact E0.

    fuel, dEb: (T, J, S) each candidate's fuel (J) and E_b change (J) per state; C: (T, S, S)
    switching costs C[k, s_prev, s]; mask: (T,) steps that count (others keep state and E_b);
    s_init: the state before step 0 (-1: free, no switching cost). Terminal cost lam_end
    (E - goal) + penalty |E - goal|. A candidate that leaves the grid costs `big`, and no value
    exceeds it (as the kernel's)."""
    fuel, dEb, C = (np.asarray(a, float) for a in (fuel, dEb, C))
    T, J, S = fuel.shape
    dE = E_max / (n_E - 1)
    grid = np.arange(n_E) * dE

    def q(V1, k, E, s):  # min over candidates of fuel + V1(E + dE) in state s, and its index
        tots = []
        for j in range(J):
            v = _bound_interp(V1[:, s], E + dEb[k, j, s], dE, n_E)
            tots.append(big if v is None else fuel[k, j, s] + v)
        return min(tots), int(np.argmin(tots))

    # V[k]: (n_E, S) value before step k at E_b grid point i, given the state before the step
    V = [None] * (T + 1)
    term = lam_end * (grid - goal) + penalty * np.abs(grid - goal)
    V[T] = np.repeat(term[:, None], S, axis=1)
    for k in range(T - 1, -1, -1):
        if not mask[k]:
            V[k] = V[k + 1]
            continue
        V[k] = np.empty((n_E, S))
        for i in range(n_E):
            Q = [q(V[k + 1], k, grid[i], s)[0] for s in range(S)]
            for sp in range(S):
                V[k][i, sp] = min(min(C[k, sp, s] + Q[s] for s in range(S)), big)
    state, cand, cost, E_path = (np.zeros(T, int), np.zeros(T, int), np.zeros(T), np.zeros(T))
    E, s = float(E0), int(s_init)
    for k in range(T):
        E_path[k] = E
        if not mask[k]:
            state[k] = max(s, 0)
            s = state[k]
            continue
        tots = []
        for s1 in range(S):
            qv, j = q(V[k + 1], k, E, s1)
            tots.append((qv + (C[k, s, s1] if s >= 0 else 0.0), j))
        s1 = int(np.argmin([t for t, _ in tots]))
        j = tots[s1][1]
        state[k], cand[k] = s1, j
        cost[k] = fuel[k, j, s1] + (C[k, s, s1] if s >= 0 else 0.0)
        E, s = E + dEb[k, j, s1], s1
    u = E0 / dE
    i0 = min(max(int(math.floor(u)), 0), n_E - 2)
    # the costate at the start on an interval of feasible values (the one below where one
    # above mixes in the infeasible), within Level 2's bracket
    v0 = V[0][:, state[0]]
    clean = [x < 1e-3 * big for x in v0]
    if clean[i0] and not clean[i0 + 1] and i0 > 0 and clean[i0 - 1]:
        lam0 = (v0[i0] - v0[i0 - 1]) / dE
    else:
        lam0 = (v0[i0 + 1] - v0[i0]) / dE
    lam0 = min(max(lam0, LAM_BRACKET[0]), LAM_BRACKET[1])
    # the value at E0 of the first decision: that of the start state, or the best when free
    first = [q(V[1], 0, E0, s1)[0] + (C[0, s_init, s1] if s_init >= 0 else 0.0)
             for s1 in range(S)] if mask[0] else None
    value = float(min(first)) if first is not None else float("nan")
    return RefBound(state=state, cand=cand, cost=cost, E=E_path, E_end=E, lam0=float(lam0),
                    value=value)


def ref_bound_pieces(mask, E, E_end, d, goal, E_max, n_E, K):
    """`bound.bound_pieces` as a loop: walk the DP's path E (T,) (E_end after it), open
    a new piece (at most K) at each counted step (mask (T,)) after the first where the path
    comes within half a grid cell (E_max / (n_E - 1)) of a limit or leaves it (a step that
    does not count is at none); add each counted step's change less its drift d (T,) to its
    piece; the last piece also gets goal - E_end. Returns (pid (T,), target (K,))."""
    E, d = np.asarray(E, float), np.asarray(d, float)
    T = E.shape[0]
    tol = 0.5 * E_max / (n_E - 1)
    pid, target = np.zeros(T, int), np.zeros(K)
    p, was = 0, None
    for k in range(T):
        at = bool(mask[k]) and (E[k] <= tol or E[k] >= E_max - tol)
        if mask[k]:
            if was is not None and at != was:
                p = min(p + 1, K - 1)
            nxt = E[k + 1] if k + 1 < T else E_end
            target[p] += nxt - E[k] - d[k]
        was = at
        pid[k] = p
    target[p] += goal - E_end
    return pid, target


def ref_excursion_pieces(E0, E_max, dE, pid, target, share=0.01):
    """`plan.excursion_pieces` as a loop over each piece's steps: walk its path from
    where the targets put its start (E0 plus the targets before it, within [0, E_max]) without
    the limits; at the first step whose end lies furthest beyond a limit, if that is more than
    share * E_max and not the piece's last step, end the piece there at
    clip(goal - what the rest of the piece adds, 0, E_max) (goal: where the targets put the
    piece's end, within the limits) and give the rest its steps and target. Returns (pid (T,),
    target (2K,)): piece p's parts are 2p and 2p + 1."""
    dE, pid, target = np.asarray(dE, float), np.asarray(pid), np.asarray(target, float)
    K, T = target.shape[0], dE.shape[0]
    new_pid, new_target = 2 * pid, np.zeros(2 * K)
    cum = E0 + np.cumsum(target)
    for p in range(K):
        steps = [k for k in range(T) if pid[k] == p]
        new_target[2 * p] = target[p]
        start = min(max(cum[p] - target[p], 0.0), E_max)
        goal = min(max(cum[p], 0.0), E_max)
        E, worst, t_s = start, -np.inf, None
        for k in steps:
            E += dE[k]
            if max(-E, E - E_max) > worst:
                worst, t_s = max(-E, E - E_max), k
        if not steps or worst <= share * E_max or t_s == steps[-1]:
            continue
        rest = [k for k in steps if k > t_s]
        t1 = min(max(goal - sum(dE[k] for k in rest), 0.0), E_max) - start
        new_target[2 * p], new_target[2 * p + 1] = t1, target[p] - t1
        new_pid[rest] = 2 * p + 1
    return new_pid, new_target


def brute_bound(fuel, dEb, C, s_init, E0, E_max, goal, lam_end, penalty):
    """The least total cost (J) of dp-bound's problem by enumerating every sequence of states
    and candidates (T steps, every step counts): the fuel and switching costs plus the terminal
    cost, E_b within [0, E_max] after every step. For tiny T only ((J S)^T sequences); where
    every E_b change is a multiple of the grid spacing the DP's interpolation is exact and
    its optimum must equal this."""
    fuel, dEb, C = (np.asarray(a, float) for a in (fuel, dEb, C))
    T, J, S = fuel.shape
    # vectorised over all sequences of the steps so far: (n,) cost, E, state
    cost, E, s = np.zeros(1), np.full(1, float(E0)), np.full(1, int(s_init))
    ok = np.ones(1, bool)
    for k in range(T):
        j, s1 = np.meshgrid(np.arange(J), np.arange(S), indexing="ij")
        j, s1 = j.ravel(), s1.ravel()
        sw = np.where(s[:, None] >= 0, C[k][np.maximum(s, 0)][:, s1], 0.0)
        cost = (cost[:, None] + fuel[k, j, s1][None] + sw).ravel()
        E = (E[:, None] + dEb[k, j, s1][None]).ravel()
        ok = np.repeat(ok, J * S) & (E >= -1e-9 * E_max) & (E <= E_max * (1 + 1e-9))
        s = np.tile(s1, s.shape[0])
    total = cost + lam_end * (E - goal) + penalty * np.abs(E - goal)
    return float(np.min(np.where(ok, total, np.inf)))


__all__ += ["RefBound", "brute_bound", "ref_bound_dp"]


# ------------------------------------------------------------------------------ the plant
class RefPlantStep(NamedTuple):
    """One step of `ref_plant`: the state at its start, what it ran and what it spent."""

    s: float
    v: float
    E_b: float
    mode: int
    gear: int
    P_d: float  # at the wheels: powertrain plus service brakes
    P_e: float
    P_m: float
    P_b: float
    P_f: float  # with idling
    P_brake: float
    v_ref: float


def _state_caps(f, mode, gear, v):
    """`_caps` of one (mode, gear) at vehicle speed v, as floats (flags as bools)."""
    w = float(f.gear_ratio[gear] * f.r_d * v)
    ok, cm, ce, k, e_lo, e_hi, pe0, m_lim, pm0 = _caps(f, int(mode), w, gear == 0)
    return SimpleNamespace(ok=bool(ok), cm=bool(cm), ce=bool(ce), k=float(k), e_lo=float(e_lo),
                           e_hi=float(e_hi), pe0=float(pe0), m_lim=float(m_lim),
                           pm0=float(pm0))


def _pm_of_pb_state(f, c, P_b):
    return float(_pm_of_pb(f, c.pm0, P_b)) if c.cm else 0.0


def _pb_of_pm_state(f, c, P_m):
    return float(_pb_of_pm(f, c.pm0, P_m)) if c.cm else 0.0


def _pb_of_pbi(f, P_bi):
    """Terminal power with internal power P_bi (the physical root of eq. 7, in the form
    without cancellation: 2 P_bi / (1 + sqrt(1 + 4 beta P_bi)))."""
    P_bi = max(P_bi, -0.25 / f.beta)
    return 2.0 * P_bi / (1.0 + math.sqrt(max(1.0 + 4.0 * f.beta * P_bi, 0.0)))


def _deliverable(f, c, E_b, dt, pb_plan=math.inf):
    """The most the state delivers for dt (its motor limited by the battery's energy and, with
    the engine connected, by a plan's battery power pb_plan where finite: its motor output,
    at least 0); -inf where it cannot run."""
    m_hi = min(c.m_lim, c.pm0 + f.eta_m * _pb_of_pbi(f, max(E_b, 0.0) / dt))
    if c.ce and math.isfinite(pb_plan):
        m_hi = min(m_hi, _plan_motor(f, c, pb_plan))
    return c.e_hi + m_hi if c.ok else -math.inf


def _plan_motor(f, c, pb_plan):
    """The motor power a plan's battery power allows: its output, within [0, the limit]."""
    return min(max(_pm_of_pb_state(f, c, pb_plan), 0.0), c.m_lim)


def _capable(f, c, E_b, P_need, dt, pb_plan=math.inf):
    """The state runs and delivers P_need for dt (`_deliverable`)."""
    return _deliverable(f, c, E_b, dt, pb_plan) >= P_need - 1e-6 * abs(P_need)


def _speed_after_switch(f, v_op, F0):
    """What Level 0 asks a state switched into to run at: v_op less road load's toll over the
    longer open time (a mode and gear switch), at least 0.1 m/s."""
    return max(v_op - max(F0, 0.0) * max(f.dt_M, f.dt_G) / f.mass, 0.1)


def ref_level0_takes(vp: VehicleParams, s_from: int, s_to: int, P_need, v, grade, lam,
                     dt: float = 1.0, E_b=None) -> bool:
    """Whether Level 0 (`_protect`, as the plant's step calls it) keeps the switch from state
    s_from into s_to (index mode * n_gears + gear) at speed v (m/s) on `grade`, for the power
    P_need (W): s_to must run at v and, after the longer open time's speed loss to road load,
    at what is left (at least 0.1 m/s); E_b: the battery's energy (None: full)."""
    f = _veh(vp)
    v = float(v)
    v_after = _speed_after_switch(f, v, float(road_load(f, v, float(grade))))
    E = f.E_b_max if E_b is None else float(E_b)
    return _protect(f, vp, E, float(P_need), v, v_after, float(lam), int(s_to), int(s_from),
                    v <= 0, dt) == int(s_to)


def ref_sync_energy(vp: VehicleParams, mode0, gear0, mode1, gear1, v) -> float:
    """Synchronisation energy (J) of the switch (mode0, gear0) -> (mode1, gear1) at speed v
    (m/s), as `plant.sync_energy`: plain Python on the vehicle's floats."""
    return _sync(_veh(vp), int(mode0), int(gear0), int(mode1), int(gear1), float(v))


def _sync(f, mode0, gear0, mode1, gear1, v):
    """Synchronisation energy (J): the rise of each connected inertia's rotational energy (an
    engine slipping in gear 1 turns at idle at least; a truck without a motor spins none)."""
    w = f.gear_ratio * f.r_d * v
    out = 0.0
    parts = [(f.I_e, ENGINE_CONNECTED, f.we_min)]
    if f.has_motor > 0.5:
        parts.append((f.I_m, MOTOR_CONNECTED, 0.0))
    for inertia, flags, floor in parts:
        w0 = max(w[gear0], floor if gear0 == 0 else 0.0)
        w1 = max(w[gear1], floor if gear1 == 0 else 0.0)
        out += 0.5 * inertia * max(flags[mode1] * w1 * w1 - flags[mode0] * w0 * w0, 0.0)
    return out


def _protect(f, vp, E_b, P_need, v_op, v_after, lam, s_req, s_cur, at_rest, dt,
             pb_plan=math.inf):
    """Level 0 (`plant.protected_state`), evaluating every state: the requested state where it
    serves (at v_op, and at v_after when switched into) or at rest; else, where the current
    one serves, the current one, but where the request is another gear in the current mode
    that serves at v_op, turned at least at the engine's idle speed there, the gear strictly
    between the two nearest the requested that serves after the switch, where one does; else
    the requested mode's gear of least H that serves after the switch; else the state of least
    H that serves after; else the current one where it runs (not open) and delivers at least
    what any other could after the switch; else the state of least H that serves now; else the
    most capable. A state serves with its motor limited by the battery and, with the engine
    connected, by a plan's battery power pb_plan where finite."""
    G = f.gear_ratio.shape[0]
    S = N_MODES * G

    def caps(s, v):
        return _state_caps(f, s // G, s % G, v)

    def serves(s, v):
        return _capable(f, caps(s, v), E_b, P_need, dt, pb_plan)

    if at_rest or (serves(s_req, v_op) and (s_req == s_cur or serves(s_req, v_after))):
        return s_req
    ok_now = [serves(s, v_op) for s in range(S)]
    ok_after = [ok_now[s] and serves(s, v_after) for s in range(S)]
    H = split_table(vp, [P_need], [v_op], lam).H[0].reshape(-1)  # inf where infeasible
    if ok_now[s_cur]:
        g_cur, g_req = s_cur % G, s_req % G
        driving = v_op * float(f.gear_ratio[g_req] * f.r_d) >= f.we_min  # not in a launch
        between = [s for s in range(S) if driving and ok_now[s_req]
                   and s // G == s_req // G == s_cur // G
                   and ok_after[s] and (s % G - g_cur) * (g_req - s % G) > 0]
        return min(between, key=lambda s: abs(s % G - g_req)) if between else s_cur
    in_mode = [H[s] if ok_after[s] and s // G == s_req // G else np.inf for s in range(S)]
    if np.isfinite(min(in_mode)):
        return int(np.argmin(in_mode))
    if any(ok_after):
        return int(np.argmin([H[s] if ok_after[s] else np.inf for s in range(S)]))
    # no switch serves after its open time: stay where the current state delivers as much
    if s_cur // G != MO and _deliverable(f, caps(s_cur, v_op), E_b, dt, pb_plan) >= max(
            _deliverable(f, caps(s, v_after), E_b, dt, pb_plan) for s in range(S)
            if s != s_cur):
        return s_cur
    if any(ok_now):
        return int(np.argmin([H[s] if ok_now[s] else np.inf for s in range(S)]))
    cap = [c.e_hi + c.m_lim if c.ok else -np.inf for c in (caps(s, v_op) for s in range(S))]
    return int(np.argmax(cap))


def _top(f, mode, gear):
    """Top speed (m/s) of (mode, gear), +inf where nothing connected limits it."""
    tops = [f.we_max] if ENGINE_CONNECTED[mode] else []
    if MOTOR_CONNECTED[mode] and f.has_motor > 0.5:
        tops.append(f.wm_max)
    return min(tops) / float(f.gear_ratio[gear] * f.r_d) if tops else math.inf


def _held_top(f, mode, gear, F0, E_b, dt):
    """`plant.held_top_speed`: the top speed (m/s) of (mode, gear) where none of the next gear
    in M_c, M_e or M_m, or the same gear in M_m, faster than it, would run after a gear
    switch's open time under road load F0 with ESCAPE_MARGIN times the power of holding the
    speed left; +inf where one would, and in the open mode."""
    G = f.gear_ratio.shape[0]
    v_top = _top(f, mode, gear)
    if not math.isfinite(v_top):  # the open mode: never held
        return math.inf
    v_esc = max(v_top - max(F0, 0.0) * f.dt_G / f.mass, 0.1)
    up = min(gear + 1, G - 1)
    for m, g in ((MC, up), (ME, up), (MM, up), (MM, gear)):
        if _top(f, m, g) > v_top * (1.0 + 1e-9) and _deliverable(
                f, _state_caps(f, m, g, v_esc), E_b, dt) >= ESCAPE_MARGIN * max(F0, 0.0) * v_esc:
            return math.inf
    return v_top * (1.0 - 1e-5)


def ref_track(route: Route, pred, end_cap: bool = True) -> SimpleNamespace:
    """What the plant reads of a route and its Level 3 prediction (`plant.make_track`), by
    loops: the reference's step boundaries (positions, speeds; the steps after the trip at the
    route's end and its end speed), node positions (padding nodes beyond the end), gradients,
    heights, the first stop at or after each node (+inf / 0 where none follows) and the
    position from which the reference needs no more traction (+inf without the cap)."""
    mask = np.asarray(pred.mask, bool)
    T = mask.shape[0]
    length = float(pred.length)
    prof_s, prof_v = np.asarray(pred.profile.s, float), np.asarray(pred.profile.v, float)
    nodes = np.asarray(route.mask, bool)
    last = max(i for i in range(nodes.shape[0]) if np.asarray(pred.profile.mask)[i])
    v_end = prof_v[last]
    ref_s = [float(pred.s[k]) if mask[k] else length for k in range(T)] + [length]
    ref_v = [float(pred.v_ref[k]) if mask[k] else v_end for k in range(T)] + [v_end]
    N = nodes.shape[0]
    grid_s = [prof_s[i] if nodes[i] else length + 1.0 + i for i in range(N)]
    stop = np.asarray(route.stop, float)
    stop_s, stop_t = [np.inf] * (N + 1), [0.0] * (N + 1)
    for i in range(N):
        for j in range(i, N):
            if nodes[j] and stop[j] > 0:
                stop_s[i], stop_t[i] = prof_s[j], stop[j]
                break
    grade = np.asarray(route.grade, float)
    ds = np.broadcast_to(np.asarray(route.ds, float), grade.shape)
    rise = [0.0]
    for i in range(1, N):
        rise.append(rise[-1] + grade[i - 1] * ds[i - 1])
    pulls = [k for k in range(T) if mask[k] and float(pred.P_d[k]) > 0]
    final_s = (ref_s[pulls[-1] + 1] if pulls else ref_s[0]) if end_cap else np.inf
    return SimpleNamespace(ref_s=np.array(ref_s), ref_v=np.array(ref_v), grid_s=np.array(grid_s),
                           grade=grade, rise=np.array(rise), stop_s=np.array(stop_s),
                           stop_t=np.array(stop_t), length=length, final_s=float(final_s))


def ref_at_or_past(s: float) -> float:
    """`plant.at_or_past` in float64: s moved past rounding (1e-6 m, or 8 ulps where more)."""
    return s + max(1e-6, 8 * np.finfo(np.float64).eps * abs(s))


def ref_plant(vp: VehicleParams, track, commands, n_steps: int, dt: float, mode0: int,
              gear0: int):
    """The plant (`plant.run_plant`) as a loop over its steps, under a scripted controller.

    track: `ref_track`'s (or the plant's `Track`, its arrays read with NumPy); commands:
    (mode, gear, lam, P_b, catch_up, level0_plan), each (n_steps,), the controller's command at
    each step (P_b nan: the optimal split at lam, found by the refined brute force of
    `split_table`; level0_plan: `plant.Command`'s).
    The truck starts at the reference's first position and speed, E_b = soc0 E_b_max, in
    (mode0, gear0).
    Returns (steps: list of `RefPlantStep`, totals: dict of the run's energies (J), switch
    counts and trip time (s), final: dict of the state after the last step)."""
    f = _veh(vp)
    tk = SimpleNamespace(**{k: np.asarray(getattr(track, k), float) for k in (
        "ref_s", "ref_v", "grid_s", "grade", "rise", "stop_s", "stop_t", "length", "final_s")})
    length, final_s = float(tk.length), float(tk.final_s)
    c_mode, c_gear, c_lam, c_pb, c_up, c_l0 = (np.asarray(a) for a in commands)
    G = f.gear_ratio.shape[0]
    T = tk.ref_s.shape[0] - 1
    t_open = max(f.dt_M, f.dt_G)
    idle_power = -_engine_friction(f, f.we_min) / f.eta_e

    def v_ref_at(j, frac):
        a, b = tk.ref_v[min(max(j, 0), T)], tk.ref_v[min(max(j + 1, 0), T)]
        return a + frac * (b - a)

    def rise_at(x):
        return float(np.interp(x, tk.grid_s, tk.rise))

    s, v, E_b = float(tk.ref_s[0]), float(tk.ref_v[0]), f.soc0 * f.E_b_max
    mode, gear, open_left, dwell, served, done = int(mode0), int(gear0), 0.0, 0.0, -1.0, False
    tot = dict(fuel=0.0, road=0.0, loss_engine=0.0, loss_slip=0.0, loss_motor=0.0,
               loss_battery=0.0, loss_brake=0.0, loss_sync=0.0, mode_switches=0,
               gear_switches=0, max_shortfall=0.0, trip_time=0.0)
    steps = []
    for k in range(n_steps):
        # where the reference is: the step whose span holds s (step ends at or before s)
        s_q = ref_at_or_past(s)
        j = min(max(int(np.searchsorted(tk.ref_s[1:], s_q, side="right")), 0), T - 1)
        span = tk.ref_s[j + 1] - tk.ref_s[j]
        frac = min(max((s - tk.ref_s[j]) / span, 0.0), 1.0) if span > 0 else 0.0
        v_here, v_next = v_ref_at(j, frac), v_ref_at(j + 1, frac)
        # the next stop not yet served
        i_node = min(max(int(np.searchsorted(tk.grid_s, s_q, side="right")) - 1, 0),
                     tk.grid_s.shape[0] - 1)
        i_next = i_node if tk.stop_s[i_node] > served + 1e-6 else i_node + 1
        s_stop, t_stop = float(tk.stop_s[i_next]), float(tk.stop_t[i_next])
        d_stop = max(s_stop - s, 0.0)
        standing = dwell > 0.5 * dt
        d_left = min(d_stop, max(length - s, 0.0))
        v_tgt = 0.0 if standing else max(v_next, min(V_CRAWL, d_left / dt))
        v1_tgt = min(v_tgt, v + f.a_max * dt, max(2.0 * d_stop / dt - v, 0.0))
        ds_tgt = min(0.5 * (v + v1_tgt) * dt, d_stop)
        # the mean gradient over the distance the step is to cover
        s_end = min(s + ds_tgt, length)
        if s_end - s > 1e-3:
            grade = (rise_at(s_end) - rise_at(s)) / (s_end - s)
        else:
            i = int(np.searchsorted(tk.grid_s, s, side="right")) - 1
            grade = float(tk.grade[min(max(i, 0), tk.grade.shape[0] - 1)])
        F0 = float(road_load(f, v, grade))
        # not past the top speed of a gear the truck cannot leave for a faster state (the
        # gradient stays the one of the target's distance)
        v1_tgt = min(v1_tgt, max(_held_top(f, mode, gear, F0, E_b, dt), v))
        ds_tgt = min(0.5 * (v + v1_tgt) * dt, d_stop)
        P_req = (0.5 * f.mass * (v1_tgt**2 - v**2) + F0 * ds_tgt) / dt
        v_op = v if v > 0 else ds_tgt / dt
        lam = float(c_lam[k])

        # Level 0: what must be served, and the state the driveline takes
        at_rest = standing or (v <= 0 and v1_tgt <= 0)
        engage = (standing and not (dwell - max(t_open, dt) > 0.5 * dt)
                  and s < length - 1e-3)  # no launch at the route's end
        s_cur = mode * G + gear
        s_req = MO * G + gear if (at_rest and not engage) else int(c_mode[k]) * G + int(c_gear[k])
        a_ref = (v_next - v_here) / dt
        P_follow = max(F0 + max(f.mass * a_ref, 0.0), 0.0) * v
        P_need = min(P_req, P_follow) if v > 0 else P_req
        v_after = _speed_after_switch(f, v_op, F0)
        planned = bool(np.isfinite(c_pb[k]))
        # a plan holding the battery allows the motor its planned power in the engine's states
        pb_plan = float(c_pb[k]) if planned and not c_up[k] and c_l0[k] else math.inf
        s_new = _protect(f, vp, E_b, P_need, v_op, v_after, lam, s_req, s_cur, at_rest, dt,
                         pb_plan)
        mode1, gear1 = divmod(s_new, G)
        gear1 = gear if mode1 == MO else gear1  # the open mode keeps the gear
        mode_sw = mode1 != mode and not done
        gear_sw = gear1 != gear and not done and mode1 != MO
        opens = max(open_left, max(f.dt_M if mode_sw else 0.0, f.dt_G if gear_sw else 0.0))
        f_open = min(max(opens / dt, 0.0), 1.0)
        dU = _sync(f, mode, gear, mode1, gear1, v) if (mode_sw or gear_sw) else 0.0
        from_batt = f.has_motor > 0.5 and E_b >= dU / f.eta_m
        E_sync_b, E_sync_f = (dU / f.eta_m, 0.0) if from_batt else (0.0, dU / f.eta_e)

        # the split in the state the driveline is in
        c = _state_caps(f, mode1, gear1, v_op)
        traction = (1.0 - f_open) * c.ok
        P_dem = min(P_req, traction * (c.e_hi + c.m_lim))
        if planned and not bool(c_up[k]) and c.ce:  # recover a switch's lost speed on the
            # engine only (with the engine disconnected the battery recovers it)
            cap_plan = traction * (c.e_hi + _plan_motor(f, c, float(c_pb[k])))
            P_dem = min(P_dem, max(P_need, cap_plan))
        if planned:
            P_b = float(c_pb[k])
        elif c.cm and c.ok:
            rs = split_table(vp, [P_dem], [v_op], lam)
            P_b = float(rs.P_b[0, mode1, gear1])
        else:
            P_b = 0.0
        # never more motor power than the engine at its lowest leaves to the requirement
        P_b = min(P_b, _pb_of_pm_state(f, c, max(-c.m_lim, P_req - c.e_lo)))
        P_b = P_b if traction > 0 else 0.0
        pb_lo = _pb_of_pm_state(f, c, max(-c.m_lim, P_dem - c.e_hi))
        pb_hi = _pb_of_pm_state(f, c, c.m_lim)
        E_avail = E_b - E_sync_b
        pb_hi = min(pb_hi, _pb_of_pbi(f, E_avail / dt))
        E_ceil = max(f.soc0 * f.E_b_max, E_avail) if s_q >= final_s else f.E_b_max
        pb_lo = max(pb_lo, _pb_of_pbi(f, (E_avail - E_ceil) / dt))
        P_b = min(max(P_b, min(pb_lo, pb_hi)), pb_hi)
        if traction > 0:
            P_m = _pm_of_pb_state(f, c, P_b)
        else:
            P_m, P_b = 0.0, 0.0
        on = c.ce and traction > 0
        P_out = min(max(P_dem - P_m, c.e_lo), c.e_hi) if on else 0.0
        P_p = P_out + P_m
        P_e = c.k * P_out
        P_f = max(P_e - c.pe0, 0.0) / f.eta_e if on else 0.0
        idle = f.has_motor < 0.5 and (mode1 == MO or traction <= 0) and not done
        P_idle = idle_power if idle else 0.0

        # the motion: the target where the powertrain and brakes meet P_req, else short of it
        P_wheel = P_p + min(P_req - P_p, 0.0)
        if P_wheel < P_req - 1e-9 * (1.0 + abs(P_req)):
            a, b = 0.5 * f.mass, 0.5 * F0 * dt
            cq = -(0.5 * f.mass * v * v - b * v + P_wheel * dt)
            disc = b * b - 4.0 * a * cq
            root = (-b + math.sqrt(disc)) / (2.0 * a) if disc > 0 else 0.0
            if root > 0:
                v1, ds = root, 0.5 * (v + root) * dt
            else:  # it stops within the step: m v^2 / 2 = (F0 v / 2 - P_wheel) t_s
                den = F0 * v - 2.0 * P_wheel
                v1, ds = 0.0, 0.5 * v * (min(f.mass * v * v / den, dt) if den > 0 else dt)
            P_wheel = (0.5 * f.mass * (v1**2 - v**2) + F0 * ds) / dt
        else:
            v1, ds = v1_tgt, ds_tgt
        arrived = np.isfinite(s_stop) and d_stop - ds <= 1e-3 and not standing
        if arrived:  # at rest there at the step's end (reached rolling: the brakes take it)
            P_wheel -= 0.5 * f.mass * v1 * v1 / dt
            v1 = 0.0
        P_brake = P_wheel - P_p
        t_in = min(max(2.0 * ds / (v + v1) if v + v1 > 0 else 0.0, 0.0), dt)
        dwell1 = max(t_stop - (dt - t_in), 0.0) if arrived else max(dwell - dt, 0.0)
        served1 = s_stop if arrived else served
        s1 = s_stop if arrived else s + ds
        finished = s1 >= length - 1e-3 and not dwell1 > 0.5 * dt
        # the moment the trip ends; the step that ends it counts up to there: the share of its
        # time where a stop at the end held it, of its distance where it reaches the end
        # moving (there at its speed)
        share = 1.0
        if standing:  # at the end, a stop's time left
            t_fin = k * dt + dwell
            share = dwell / dt if finished else 1.0
        elif arrived:
            t_fin = k * dt + t_in + t_stop
        else:  # the end within the step, at its constant acceleration
            d_end = min(max(length - s, 0.0), ds)
            v_d = math.sqrt(max(v * v + 2.0 * (v1 - v) / dt * d_end, 0.0))
            t_fin = k * dt + (min(2.0 * d_end / (v + v_d), dt) if v + v_d > 0 else 0.0)
            if finished:
                share = d_end / ds if ds > 0 else 1.0
                v1, s1 = v_d, s + d_end
        E_b1 = min(max(E_b - (P_b + f.beta * P_b * P_b) * dt * share - E_sync_b, 0.0),
                   f.E_b_max)

        live = not done
        steps.append(RefPlantStep(s=s, v=v, E_b=E_b, mode=mode1, gear=gear1,
                                  P_d=P_wheel * live, P_e=P_e * live, P_m=P_m * live,
                                  P_b=P_b * live, P_f=(P_f + P_idle) * live,
                                  P_brake=P_brake * live, v_ref=v_here))
        if live:
            h = dt * share
            for key, x in (("fuel", (P_f + P_idle) * h + E_sync_f), ("road", F0 * ds * share),
                           ("loss_engine", (P_f - P_e + P_idle) * h),
                           ("loss_slip", (P_e - P_out) * h), ("loss_motor", (P_b - P_m) * h),
                           ("loss_battery", f.beta * P_b * P_b * h),
                           ("loss_brake", -P_brake * h), ("loss_sync", E_sync_b + E_sync_f)):
                tot[key] += x
            tot["mode_switches"] += int(mode_sw)
            tot["gear_switches"] += int(gear_sw)
            if not standing:
                tot["max_shortfall"] = max(tot["max_shortfall"], v_here - v)
            if finished:
                tot["trip_time"] = t_fin
            s, v, E_b, mode, gear = s1, v1, E_b1, mode1, gear1
            open_left, dwell, served = max(opens - dt, 0.0), dwell1, served1
            done = finished
    final = dict(s=s, v=v, E_b=E_b, mode=mode, gear=gear, done=done)
    return steps, tot, final


__all__ += ["RefPlantStep", "ref_level1", "ref_plant", "ref_level0_takes", "ref_sync_energy",
            "ref_track"]
