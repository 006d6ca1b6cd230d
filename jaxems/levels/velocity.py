"""Level 3: velocity prediction from the road ahead (paper section 6).

Three driving modes (maximum acceleration, minimum acceleration, cruise at v0) give the
predicted speed. On the distance grid of a `Route` (nodes s_i, cells of length ds):

    vlim_i   = min(vmax_i, v0), and 0 at stop nodes
    forward  v_{i+1} = min(vlim_{i+1}, sqrt(max(v_i^2 + 2 a ds, 0)))
             a       = min(a_fwd(v_i), a_fwd(v_pred)),  v_pred^2 = v_i^2 + 2 a_fwd(v_i) ds
             a_fwd(v) = a_t / (1 + k(v) max(a_t + F_0 / m, 0))  where a_t > 0, else a_t
             a_t(v)   = min(a_max, (F_max(v) - F_0(v, grade_i)) / m)
             F_max(v) = min(P_e_max(w_pred) / v, T_e_peak r_G(1) r_d)
             k(v)     = dt_G / (max(v, v_1) ln r)
    backward v_i = min(vlim_i, sqrt(v_{i+1}^2 + 2 a_min ds))
    v_c      = min(v_forward, v_backward)

F_max is the tractive force of the engine alone (mode M_e) behind a continuously variable
gearbox holding the engine at w_pred (the paper's 1100 rpm, `VehicleParams.w_pred`), capped at
low speed by the peak engine torque in the lowest gear. A stepped gearbox opens the driveline
for dt_G at each upshift (eq. 12): accelerating, one upshift falls in each speed step v ln r
above gear 1's top speed v_1 (r the mean ratio step), and in it the vehicle gains nothing and
loses F_0 dt_G / m to road load, so the mean acceleration is a_fwd, not a_t (without it the
reference accelerates through the shifts as a CVT would, and every launch leaves the plant a
second behind per shift; the paper's prediction has no shifts). The backward pass brakes at the
comfort limit a_min (service brakes always allowed). Taking the smaller of a_fwd at the cell's
start speed and at the predicted end speed keeps the traction force within F_max over the whole
cell (a_t decreases with v, and a_fwd <= a_t; the driveline power stays within P_e_max while the
forward pass limits the speed). Both passes are `lax.scan`s in the v^2 form (the
speed squared is linear in s at constant acceleration). The start node is entered at standstill
when it is a stop, at its limit otherwise (flying start); the end is standstill when the last
node is a stop, free otherwise.

Crawl floor: at a node that is not a stop the speed never falls below V_CRAWL (0.5 m/s, or the
node's limit if lower), so every cell takes finite time. When the forward pass would have
stalled below it (the truck cannot climb), `feasible` is False.

Time grid. Within a cell the acceleration is constant, so the cell takes 2 ds / (v_i + v_i+1)
and the vehicle stands still for `stop_i` seconds at each stop node. `resample` turns this into
T uniform steps t_k = k dt (T static; a mask marks t_k < trip time):

- s_k   position at t_k; v_k = (s_{k+1} - s_k) / dt the MEAN speed over the step, so
  sum(v_k dt) over the valid steps is the route length;
- a_k   mean acceleration (v(t_{k+1}) - v(t_k)) / dt of the instantaneous speed v(t);
- grade_k mean gradient over [s_k, s_{k+1}] (the gradient at s_k while standing);
- P_d,k mean driveline power over the step: (0.5 m (v(t_{k+1})^2 - v(t_k)^2)
  + int_{s_k}^{s_{k+1}} F_0 ds) / dt, exact for the piecewise profile (v^2 linear in s within a
  cell), so sum(P_d dt) is the kinetic-energy change plus the road-load work and nothing is
  singular at launches; standstill steps have v = 0 and P_d = 0;
- v_ref,k the instantaneous speed at t_k, the reference a speed controller tracks.

Road load follows `powertrain.road_load` (resistance positive): F_0 = F_air + F_roll + F_grade.

Eco-driving (`optimize_velocity`; the paper's future work, sections 6 and 8). Instead of
predicting, choose the node speeds v_i below Level 3's profile that minimise

    J(v) = sum_cells H*(P_d, v_mean) dt + lambda_t (sum_cells dt + stop times)

with the cell model of `resample` (constant acceleration, dt = 2 ds / (v_i + v_i+1), P_d the
exact work over the cell divided by dt) and H* the soft minimum over the 4 modes x 12 gears of
Level 1's Hamiltonian H = P_f - lambda_b P_bi (`powersplit.mode_gear_split`) at the cell's mean
power and speed: fuel-equivalent power at Level 2's battery price lambda_b. lambda_t (J/s) is
the price of time; `match_trip_time` finds the one that gives a target trip time. Constraints:
Level 3's profile as the upper bound (vmax, v0, traction, comfort braking, start and end),
0 at stops, V_CRAWL elsewhere, the first and last node as Level 3's, and per cell
-a_min <= a <= a_fwd(v_i, grade_i). The optimiser is projected Adam on v (`project_speeds` after
each step) over a table of H* (`eco_table`), from Level 3 capped at the best flat-road cruise
speed (`cruise_speed`). The surrogate has no switching costs and no battery limits (Level 2 and
Level 1 add them when they run on the optimised profile); alone, its optimum is a pulse-and-glide
sawtooth of cell-scale period (engine on, engine off) that costs mode switches, so the optimiser
adds `eco_regulariser`, switch_weight x the total variation of the acceleration.
"""

from __future__ import annotations

import collections
import math
import numbers
from collections.abc import Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import powertrain as pt
from ..params import VehicleParams, check_vehicle, stack_vehicles
from ..route import Route, check_route, pad_routes
from ..xla import jit
from .powersplit import mode_gear_split

V_CRAWL = 0.5  # m/s: lowest speed away from stops
V_BIG = 1.0e3  # m/s: "no limit" on padding nodes
STEP_BUCKET = 256  # time steps are rounded up to a multiple of this
TRACES: collections.Counter = collections.Counter()  # trace counts of the jitted entry points


class Profile(NamedTuple):
    """Level 3 speed on the distance grid of one route; shapes (N,) per node.

    s: node positions (m); v: predicted speed v_c (m/s); v_fwd, v_bwd: the forward and backward
    passes (m/s); vlim: min(vmax, v0), 0 at stops (m/s); t_arr, t_dep: arrival and departure
    time at each node (s; they differ by the stop time); mask: valid nodes; trip_time: () s,
    departure from the last node (final stop included); length: () m; feasible: () bool, False
    when the truck would stall away from a stop (the crawl floor was used).
    """

    s: Any
    v: Any
    v_fwd: Any
    v_bwd: Any
    vlim: Any
    t_arr: Any
    t_dep: Any
    mask: Any
    trip_time: Any
    length: Any
    feasible: Any


class Prediction(NamedTuple):
    """Level 3 output on the time grid; shapes (T,) per step unless noted.

    t: step start times k dt (s); s: position at t_k (m); v: mean speed over the step (m/s);
    a: mean acceleration (m/s^2); grade: mean gradient (rise/run); P_d: mean driveline power
    demand (W, positive driving); v_ref: instantaneous speed at t_k (m/s); mask: t_k < trip
    time; dt: () s; trip_time: () s; length: () m; feasible: () bool; profile: the `Profile`
    on the distance grid (v(s) for a controller indexed by position).
    """

    t: Any
    s: Any
    v: Any
    a: Any
    grade: Any
    P_d: Any
    v_ref: Any
    mask: Any
    dt: Any
    trip_time: Any
    length: Any
    feasible: Any
    profile: Profile


# ------------------------------------------------------------------------------ distance grid
def traction_limit(vp: VehicleParams, v, w_pred):
    """F_max (N): engine-only tractive force at speed v behind a CVT holding w_pred (rad/s).

    min(P_e_max(w_pred) / v, T_e_peak r_G(1) r_d): power-limited, torque-limited near 0.
    """
    _, p_max = pt.engine_power_limits(vp, w_pred)
    f_torque = jnp.max(vp.te_max) * vp.gear_ratio[0] * vp.r_d
    return jnp.minimum(p_max / jnp.maximum(v, 1e-6), f_torque)


def shift_time_per_speed(vp: VehicleParams, v):
    """(s per m/s) open-driveline time of the upshifts per unit of speed gained at speed v.

    Accelerating through a gearbox whose ratios step by r, one upshift falls in each speed
    interval dv = v ln r above gear 1's top speed v_1 = w_max / (r_G(1) r_d); each opens the
    driveline for dt_G (eq. 12). r is the mean step of the vehicle's ratios; with one gear, or
    gears of one ratio, nothing is shifted (0)."""
    n = vp.gear_ratio.shape[-1]
    v = jnp.asarray(v, dtype=jnp.result_type(v, float))
    if n < 2:
        return jnp.zeros_like(v)
    ln_r = jnp.abs(jnp.log(vp.gear_ratio[..., 0] / vp.gear_ratio[..., -1])) / (n - 1)
    v1 = vp.we_max / (jnp.max(vp.gear_ratio, axis=-1) * vp.r_d)
    shifts = ln_r > 1e-9
    return jnp.where(shifts, vp.dt_G / (jnp.maximum(v, v1) * jnp.where(shifts, ln_r, 1.0)), 0.0)


def forward_acceleration(vp: VehicleParams, v, grade, w_pred):
    """a_fwd (m/s^2): full traction, a = min(a_max, (F_max(v) - F_0(v, grade)) / m), slowed by
    the upshifts on the way: a / (1 + k(v) max(a + F_0 / m, 0)) where a > 0, k the upshifts'
    open time per m/s (`shift_time_per_speed`). During each shift the vehicle loses
    F_0 dt_G / m of speed and gains nothing, so a speed step dv takes dv / a plus
    k dv (1 + F_0 / (m a)): the mean acceleration a driveline with a stepped gearbox achieves."""
    f0 = pt.road_load(vp, v, grade)
    a = jnp.minimum(vp.a_max, (traction_limit(vp, v, w_pred) - f0) / vp.mass)
    k = shift_time_per_speed(vp, v)
    return jnp.where(a > 0, a / (1.0 + k * jnp.maximum(a + f0 / vp.mass, 0.0)), a)


def _limits(route: Route, vp: VehicleParams):
    """(mask, ds, is_stop, vlim, floor) of one route: vlim = min(vmax, v0), 0 at stops and V_BIG
    on padding; floor = 0 at stops, min(V_CRAWL, vlim) elsewhere. Shapes (N,) and ()."""
    grade = jnp.asarray(route.grade)
    dtype = grade.dtype
    mask = jnp.asarray(route.mask)
    ds = jnp.asarray(route.ds, dtype)
    is_stop = (jnp.asarray(route.stop) > 0) & mask
    vlim = jnp.minimum(jnp.asarray(route.vmax, dtype), vp.v_cruise)
    vlim = jnp.where(is_stop, 0.0, vlim)
    vlim = jnp.where(mask, vlim, V_BIG)
    floor = jnp.where(is_stop, 0.0, jnp.minimum(V_CRAWL, vlim))
    return mask, ds, is_stop, vlim, floor


def velocity_profile(route: Route, vp: VehicleParams, w_pred=None) -> Profile:
    """Level 3 on the distance grid for ONE route and ONE vehicle (jit/vmap-able).

    route: leaves (N,) and (); vp: one vehicle; w_pred: engine speed (rad/s) Level 3 assumes,
    () or (N,) per node (default vp.w_pred; the iteration scheme feeds back the gear sequence).
    """
    grade = jnp.asarray(route.grade)
    N = grade.shape[-1]
    dtype = grade.dtype
    mask, ds, _, vlim, floor = _limits(route, vp)
    w = jnp.broadcast_to(jnp.asarray(vp.w_pred if w_pred is None else w_pred, dtype), (N,))

    def fwd(v, xs):
        g, w_i, lim_next, floor_next, valid = xs
        # predictor-corrector: the smaller of a_fwd at the start speed and at the predicted end
        # speed, so the traction force never exceeds F_max anywhere in the cell
        a1 = forward_acceleration(vp, v, g, w_i)
        v_pred = jnp.sqrt(jnp.maximum(v * v + 2.0 * a1 * ds, 0.0))
        a = jnp.minimum(a1, forward_acceleration(vp, v_pred, g, w_i))
        v2 = v * v + 2.0 * a * ds
        stalled = valid & (a < 0) & (v2 < floor_next * floor_next)
        v_next = jnp.minimum(lim_next, jnp.sqrt(jnp.maximum(v2, 0.0)))
        v_next = jnp.maximum(v_next, floor_next)
        return v_next, (v_next, stalled)

    v0 = vlim[0]  # 0 at a starting stop, the limit otherwise (flying start)
    _, (v_f, stalled) = jax.lax.scan(fwd, v0, (grade[:-1], w[:-1], vlim[1:], floor[1:], mask[1:]))
    v_fwd = jnp.concatenate([v0[None], v_f])

    def bwd(v, lim):
        v_i = jnp.minimum(lim, jnp.sqrt(v * v + 2.0 * vp.a_min * ds))
        return v_i, v_i

    _, v_b = jax.lax.scan(bwd, vlim[-1], vlim[:-1], reverse=True)
    v_bwd = jnp.concatenate([v_b, vlim[-1:]])
    v = jnp.where(mask, jnp.minimum(v_fwd, v_bwd), 0.0)
    return profile_from_speed(route, vp, v, v_fwd, v_bwd, feasible=~jnp.any(stalled))


def profile_from_speed(
    route: Route, vp: VehicleParams, v, v_fwd=None, v_bwd=None, feasible=True
) -> Profile:
    """A `Profile` of ONE route from any node speeds v: (N,) m/s (jit/vmap-able).

    Computes the timing exactly as `velocity_profile` does (cell time 2 ds / (v_i + v_i+1),
    the sum floored at V_CRAWL; stop times at stop nodes): t_arr, t_dep, trip_time, and vlim,
    s, mask, length. v is zeroed on padding; v_fwd, v_bwd: (N,) the passes to record (default
    v); feasible: () bool to record. `resample` then turns the profile into a time grid.
    """
    grade = jnp.asarray(route.grade)
    N = grade.shape[-1]
    dtype = grade.dtype
    mask, ds, _, vlim, _ = _limits(route, vp)
    v = jnp.where(mask, jnp.asarray(v, dtype), 0.0)
    v_fwd = v if v_fwd is None else jnp.asarray(v_fwd, dtype)
    v_bwd = v if v_bwd is None else jnp.asarray(v_bwd, dtype)
    cell_valid = mask[1:]
    dt_cell = jnp.where(cell_valid, 2.0 * ds / jnp.maximum(v[:-1] + v[1:], V_CRAWL), 0.0)
    stop = jnp.where(mask, jnp.asarray(route.stop, dtype), 0.0)
    # arrival at i+1 = arrival at i + stop_i + dt_cell_i
    t_arr = jnp.concatenate([jnp.zeros(1, dtype), jnp.cumsum(stop[:-1] + dt_cell)])
    t_dep = t_arr + stop
    trip_time = jnp.max(jnp.where(mask, t_dep, 0.0))
    s = jnp.arange(N, dtype=dtype) * ds
    return Profile(
        s=s,
        v=v,
        v_fwd=jnp.where(mask, v_fwd, 0.0),
        v_bwd=jnp.where(mask, v_bwd, 0.0),
        vlim=jnp.where(mask, vlim, 0.0),
        t_arr=t_arr,
        t_dep=t_dep,
        mask=mask,
        trip_time=trip_time,
        length=jnp.asarray(route.length, dtype),
        feasible=jnp.asarray(feasible, bool),
    )


# ---------------------------------------------------------------------------------- time grid
def _cell_state(route: Route, vp: VehicleParams, prof: Profile, t):
    """Position s(t), speed v(t), road work W(s(t)) and gradient at times t (any shape)."""
    v = prof.v
    N = v.shape[-1]
    dtype = v.dtype
    ds = jnp.asarray(route.ds, dtype)
    grade = jnp.asarray(route.grade, dtype)
    t_dep = jnp.where(prof.mask, prof.t_dep, jnp.inf)
    i = jnp.clip(jnp.searchsorted(t_dep, t, side="right") - 1, 0, N - 2)
    vi, vn = v[i], v[i + 1]
    dt_c = prof.t_arr[i + 1] - prof.t_dep[i]
    moving = prof.mask[i + 1] & (dt_c > 0)
    x = jnp.clip((t - prof.t_dep[i]) / jnp.where(moving, dt_c, 1.0), 0.0, 1.0)
    x = jnp.where(moving, x, 0.0)
    vsum = vi + vn
    regular = vsum >= V_CRAWL  # the same threshold as the cell time in velocity_profile
    # fraction of the cell covered: constant acceleration (or uniform motion if degenerate)
    frac = jnp.where(regular, (2.0 * vi * x + (vn - vi) * x * x) / jnp.where(regular, vsum, 1.0), x)
    v_t = jnp.where(regular, vi + (vn - vi) * x, ds / jnp.where(moving, dt_c, 1.0))
    v_t = jnp.where(moving, v_t, 0.0)
    s_t = jnp.minimum(i * ds + frac * ds, prof.length)
    # road work: per cell F_0 = k_air v^2 + F_g(grade); v^2 linear in s within the cell
    k_air, f_grade = _road_forces(route, vp, dtype)
    cell_w = jnp.where(prof.mask[1:], _cell_work(route, vp, v), 0.0)
    W_nodes = jnp.concatenate([jnp.zeros(1, dtype), jnp.cumsum(cell_w)])
    y = frac  # fraction of the cell's distance
    W_t = W_nodes[i] + jnp.where(
        prof.mask[i + 1],
        (k_air * (vi**2 * y + (vn**2 - vi**2) * y * y / 2.0) + f_grade[i] * y) * ds,
        0.0,
    )
    return s_t, v_t, W_t, grade[i], i


def resample(route: Route, vp: VehicleParams, prof: Profile, dt, n_steps: int) -> Prediction:
    """Level 3 on the uniform time grid t_k = k dt, k < n_steps (static) for ONE route.

    Returns a `Prediction` with (n_steps,) arrays; steps at or after the trip time are masked
    out and zero (v, a, P_d), with s at the route end.
    """
    dtype = prof.v.dtype
    dt = jnp.asarray(dt, dtype)
    tk = jnp.arange(n_steps + 1, dtype=dtype) * dt
    s_t, v_t, W_t, g_i, _ = _cell_state(route, vp, prof, tk)
    # from the trip time on, the state is the end of the route (its final speed)
    done = tk >= prof.trip_time
    v_end = jnp.sum(jnp.where(last_node(prof.mask), prof.v, 0.0))
    s_t = jnp.where(done, prof.length, s_t)
    v_t = jnp.where(done, v_end, v_t)
    ds_k = jnp.diff(s_t)
    mask = ~done[:-1]
    v_mean = ds_k / dt
    a_mean = jnp.diff(v_t) / dt
    # mean gradient over the step from the cumulative rise (tan form, exact per cell)
    ds_r = jnp.asarray(route.ds, dtype)
    rise_t = jnp.interp(s_t, prof.s, node_rise(route, dtype))
    moving = ds_k > 1e-9 * ds_r
    g_mean = jnp.where(moving, jnp.diff(rise_t) / jnp.where(moving, ds_k, 1.0), g_i[:-1])
    E_kin = 0.5 * vp.mass * v_t * v_t
    W_end = _total_work(route, vp, prof)
    W_t = jnp.where(done, W_end, W_t)
    P_d = (jnp.diff(E_kin) + jnp.diff(W_t)) / dt
    zero = jnp.zeros_like(v_mean)
    return Prediction(
        t=tk[:-1],
        s=s_t[:-1],
        v=jnp.where(mask, v_mean, zero),
        a=jnp.where(mask, a_mean, zero),
        grade=jnp.where(mask, g_mean, zero),
        P_d=jnp.where(mask & moving, P_d, zero),
        v_ref=jnp.where(mask, v_t[:-1], zero),
        mask=mask,
        dt=dt,
        trip_time=prof.trip_time,
        length=prof.length,
        feasible=prof.feasible,
        profile=prof,
    )


def last_node(mask):
    """(N,) bool: True at the last valid entry of a mask (a route's last node, a prediction's
    last step)."""
    return mask & ~jnp.concatenate([mask[1:], jnp.zeros(1, bool)])


def node_rise(route: Route, dtype=None):
    """(N,) height (m) of each node of one route above its start: the sum of grade * ds over
    the cells before it. Interpolated linearly in s, its difference over [s_a, s_b] divided by
    s_b - s_a is the mean gradient there, exact per cell (Level 3's steps, the plant's)."""
    grade = jnp.asarray(route.grade, dtype)
    ds = jnp.asarray(route.ds, grade.dtype)
    return jnp.concatenate([jnp.zeros(1, grade.dtype), jnp.cumsum(grade[:-1] * ds)])


def _road_forces(route: Route, vp: VehicleParams, dtype):
    """(k_air () N s^2/m^2, f_grade (N,) N): F_0 = k_air v^2 + f_grade per cell, f_grade the
    rolling and grade force (`powertrain.road_load` at v = 0)."""
    k_air = 0.5 * vp.c_w * vp.area * vp.rho
    return k_air, pt.road_load(vp, 0.0, jnp.asarray(route.grade, dtype))


def _cell_work(route: Route, vp: VehicleParams, v):
    """(N-1,) road-load work (J) over each cell at node speeds v: (N,), v^2 linear in s within
    the cell (constant acceleration), so int F_0 ds = (k_air (v_i^2 + v_i+1^2) / 2 + f_grade) ds.
    Padding cells are not masked."""
    k_air, f_grade = _road_forces(route, vp, v.dtype)
    ds = jnp.asarray(route.ds, v.dtype)
    return (k_air * 0.5 * (v[:-1] ** 2 + v[1:] ** 2) + f_grade[:-1]) * ds


def _total_work(route: Route, vp: VehicleParams, prof: Profile):
    return jnp.sum(jnp.where(prof.mask[1:], _cell_work(route, vp, prof.v), 0.0))


# ----------------------------------------------------------------------------- host wrappers
_profile_jit = jit(velocity_profile)
_resample_jit = jit(resample, static_argnames=("n_steps",))
_profile_vmap = jit(jax.vmap(velocity_profile, in_axes=(0, 0, 0)))


def _resample_batch(routes, vehicles, profs, dt, n_steps):
    return jax.vmap(lambda r, v, p: resample(r, v, p, dt, n_steps))(routes, vehicles, profs)


_resample_vmap = jit(_resample_batch, static_argnames=("n_steps",))


def steps_for(trip_time: float, dt: float, bucket: int = STEP_BUCKET) -> int:
    """Static number of time steps covering `trip_time`, rounded up to a multiple of `bucket`."""
    n = int(math.floor(trip_time / dt)) + 2
    return int(math.ceil(n / bucket) * bucket)


def _w_pred_array(vp: VehicleParams, w_pred, n: int):
    return jnp.broadcast_to(jnp.asarray(vp.w_pred if w_pred is None else w_pred), (n,))


def predict_velocity(
    route: Route,
    vehicle: VehicleParams,
    dt: float = 1.0,
    n_steps: int | None = None,
    w_pred=None,
) -> Prediction:
    """Level 3 speed and power prediction for one route and one vehicle.

    route: one `Route` (see `jaxems.load_route`); vehicle: `VehicleParams` (mass, limits,
    v_cruise as v0, w_pred); dt: time step T_k (s); n_steps: static number of steps (default:
    enough for the trip, rounded up to a multiple of 256); w_pred: () or (N,) engine speed
    (rad/s) per node, default vehicle.w_pred. Returns a `Prediction` with (n_steps,) arrays.
    Raises ValueError when n_steps is too small for the trip.
    """
    if not (isinstance(dt, numbers.Real) and not isinstance(dt, bool) and dt > 0
            and math.isfinite(dt)):
        raise ValueError(f"dt must be a positive number of seconds (got {dt!r})")
    dt = float(dt)
    if np.ndim(route.ds) != 0 or np.ndim(vehicle.mass) != 0:
        raise ValueError("predict_velocity takes one route and one vehicle; use predict_batch")
    check_vehicle(vehicle)
    route = check_route(route)
    N = np.shape(route.grade)[-1]
    prof = _profile_jit(route, vehicle, _w_pred_array(vehicle, w_pred, N))
    trip = float(prof.trip_time)
    need = int(math.floor(trip / dt)) + 1
    if n_steps is None:
        n_steps = steps_for(trip, dt)
    elif n_steps < need:
        raise ValueError(
            f"n_steps={n_steps} too small: the trip takes {trip:.1f} s ({need} steps of {dt:g} s)"
        )
    return _resample_jit(route, vehicle, prof, dt, n_steps=n_steps)


def _batch_size(leaf) -> int | None:
    return int(np.shape(leaf)[0]) if np.ndim(leaf) >= 1 else None


def _paired_batch(routes, vehicles, w_pred, name: str, single: str):
    """Routes and vehicles of a batch entry point paired one to one: (routes (B, N) leaves,
    vehicles (B,) leaves, w (B, N) rad/s). A list is padded / stacked; a single route or
    vehicle is repeated B times; w_pred None means each vehicle's own. name, single: the
    caller and its one-configuration form, for the messages."""
    if not isinstance(routes, Route):
        routes = pad_routes(list(routes))
    if not isinstance(vehicles, VehicleParams):
        vehicles = stack_vehicles(list(vehicles))
    check_vehicle(vehicles)
    routes = check_route(routes)
    br = _batch_size(routes.ds)
    bv = _batch_size(vehicles.mass)
    if br is None and bv is None:
        raise ValueError(f"{name}: neither routes nor vehicles are a batch; use {single}")
    if br is not None and bv is not None and br != bv:
        raise ValueError(f"{name}: {br} routes but {bv} vehicles (pair them one to one)")
    B = br if br is not None else bv
    if br is None:
        routes = Route(*(np.broadcast_to(np.asarray(x), (B, *np.shape(x))) for x in routes))
    if bv is None:
        vehicles = VehicleParams(
            *(np.broadcast_to(np.asarray(x), (B, *np.shape(x))) for x in vehicles)
        )
    N = np.shape(routes.grade)[-1]
    dtype = np.result_type(np.asarray(routes.grade).dtype, np.float32)
    w = vehicles.w_pred if w_pred is None else w_pred
    w = np.asarray(w, dtype)
    w = np.broadcast_to(w[:, None] if w_pred is None else w, (B, N))
    return routes, vehicles, w


def predict_batch(
    routes: Route | Sequence[Route],
    vehicles: VehicleParams | Sequence[VehicleParams],
    dt: float = 1.0,
    n_steps: int | None = None,
    w_pred=None,
) -> Prediction:
    """Level 3 for a batch, through `vmap`; results equal a loop of `predict_velocity`.

    routes: a list of `Route`s (padded with `pad_routes`) or a padded batch (leaves (B, N));
    vehicles: a list or a stacked batch (`stack_vehicles`) of B vehicles, or one vehicle.
    w_pred: None (each vehicle's w_pred), or rad/s broadcastable to (B, N): a scalar, (N,) per
    node, (B, 1) per member or (B, N).
    A single route with a batch of vehicles is also accepted. Batches are paired element by
    element (route b with vehicle b); for every combination, repeat them. All members share
    one static number of steps (the longest trip). Returns a `Prediction` with leading axis B.
    """
    routes, vehicles, w = _paired_batch(routes, vehicles, w_pred, "predict_batch",
                                        "predict_velocity")
    prof = _profile_vmap(routes, vehicles, w)
    trip = float(jnp.max(prof.trip_time))
    need = int(math.floor(trip / dt)) + 1
    if n_steps is None:
        n_steps = steps_for(trip, dt)
    elif n_steps < need:
        raise ValueError(f"n_steps={n_steps} too small: the longest trip takes {trip:.1f} s")
    return _resample_vmap(routes, vehicles, prof, dt, n_steps=n_steps)


def energy_summary(pred: Prediction) -> dict:
    """Host-side totals of one prediction: trip time, mean speed, traction and braking energy."""
    m = np.asarray(pred.mask)
    P = np.asarray(pred.P_d)[m]
    dt = float(pred.dt)
    trip = float(pred.trip_time)
    return {
        "trip_time_s": trip,
        "length_m": float(pred.length),
        "mean_speed_km_h": float(pred.length) / trip * 3.6 if trip > 0 else 0.0,
        "energy_traction_MJ": float(np.sum(np.maximum(P, 0.0)) * dt / 1e6),
        "energy_braking_MJ": float(np.sum(np.minimum(P, 0.0)) * dt / 1e6),
        "energy_net_MJ": float(np.sum(P) * dt / 1e6),
        "P_d_max_kW": float(P.max() / 1e3) if P.size else 0.0,
        "P_d_min_kW": float(P.min() / 1e3) if P.size else 0.0,
        "feasible": bool(pred.feasible),
        "steps": int(m.sum()),
    }


# =============================================================================================
# Eco-driving: velocity optimisation on the distance grid (the paper's "future work", section 8)
# =============================================================================================
TAU_W = 100.0  # W: default temperature of the soft minimum over modes and gears
P_PENALTY_W = 1.0e6  # W: Hamiltonian of a cell whose demand no (mode, gear) can deliver
N_STEPS = 1500  # default Adam steps of `optimize_velocity`
LEARNING_RATE = 0.3  # m/s: default first step size
FINAL_LR_RATIO = 3e-3  # the step size decays to this fraction over the steps
ADAM_B2 = 0.99  # Adam's second-moment decay (shorter memory than optax's 0.999: kinks)
N_BISECT = 12  # default bisection steps of `match_trip_time`
SWITCH_WEIGHT = 1.0e5  # J/(m/s^2): default weight of `eco_regulariser`
ACC_EPS = 0.01  # m/s^2: smoothing of the total variation in `eco_regulariser`
BIG_V2 = 1.0e12  # (m/s)^2: "no constraint" in the min-plus scans of `project_speeds`
LAMBDA_T_RANGE = (1.0e2, 1.0e7)  # J/s: bracket of `match_trip_time` (searched in log scale)
MATCH_RTOL = 5e-3  # relative trip-time tolerance of `match_trip_time`

# status bit flags of an `EcoResult`
ECO_OK = 0
ECO_STALL = 1  # Level 3's envelope stalled (crawl floor used): the acceleration limit is broken
ECO_NONFINITE = 2  # the objective was not finite: Level 3's profile is returned
ECO_TARGET_FAST = 4  # match_trip_time: target faster than the fastest optimum (the envelope)
ECO_TARGET_SLOW = 8  # match_trip_time: target slower than the optimum at the smallest lambda_t
ECO_TARGET_MISSED = 16  # match_trip_time: the trip time is off the target by more than 0.5 %
ECO_STATUS_NAMES = {
    ECO_STALL: "level3-stall",
    ECO_NONFINITE: "non-finite",
    ECO_TARGET_FAST: "target-too-fast",
    ECO_TARGET_SLOW: "target-too-slow",
    ECO_TARGET_MISSED: "target-missed",
}


def eco_status_names(code: int) -> list[str]:
    """Names of the flags set in an `EcoResult.status` (host-side)."""
    return [name for bit, name in ECO_STATUS_NAMES.items() if int(code) & bit]


class EcoCells(NamedTuple):
    """The cell model of the eco-driving objective; shapes (N-1,) per cell i (nodes i, i+1).

    P_d: mean driveline power over the cell (W); v_mean: mean speed ds / dt (m/s); dt: cell time
    (s, 0 on padding); H: minimised Hamiltonian (W; soft or hard minimum over modes and gears,
    P_PENALTY_W + 2 P_d / eta_e where nothing can deliver P_d); energy: H dt (J, fuel
    equivalent, 0 on padding); valid: bool, a cell of the route (not padding).
    """

    P_d: Any
    v_mean: Any
    dt: Any
    H: Any
    energy: Any
    valid: Any


class EcoResult(NamedTuple):
    """Result of `optimize_velocity` for one route and one vehicle (leading batch axis B from
    `optimize_velocity_batch`).

    profile: `Profile` of the optimised speeds (v: (N,) m/s; v_fwd, v_bwd: Level 3's passes,
    whose minimum is Level 3's speed); v_level3: (N,) Level 3's speeds; v_upper: (N,) the upper
    bound (`speed_bounds`: Level 3's speeds with the overspeed band);
    cost: () J, surrogate objective (soft minimum over modes/gears, temperature tau) of the
    returned speeds; cost_exact: () J, the same with the exact (hard) minimum; regulariser: ()
    J, the switching proxy `eco_regulariser` of the returned speeds (not in cost); energy_J: () J,
    fuel-equivalent energy sum(H dt) with the hard minimum (fuel + |lambda_b| x battery energy);
    trip_time: () s; lambda_t: () J/s the time price used; acc_violation: () m/s^2, the
    largest acceleration-limit violation of the optimiser's iterate before the feasibility
    restoration (the returned profile is restored); grad_norm: () J/(m/s), norm of the
    gradient at that iterate without the components the bounds block; history: (n_steps,) J,
    the objective the optimiser steps on (tabulated soft minimum) at each iterate; status: ()
    int32 bit flags (ECO_*, names from `eco_status_names`).
    """

    profile: Profile
    v_level3: Any
    v_upper: Any
    cost: Any
    cost_exact: Any
    regulariser: Any
    energy_J: Any
    trip_time: Any
    lambda_t: Any
    acc_violation: Any
    grad_norm: Any
    history: Any
    status: Any


def soft_min_hamiltonian(H, P_d, vp: VehicleParams, tau=None):
    """Soft minimum of H over modes and gears: (..., 4, G) -> (...,) (W).

    tau: temperature (W) of -tau log sum exp(-H / tau), or None for the exact minimum. Entries
    with H = +inf (infeasible) are masked out before exp/log (double where: finite values and
    finite gradients everywhere); where no entry is feasible (P_d beyond every mode's
    capability, P_d > 0) the result is P_PENALTY_W + 2 P_d / eta_e, finite and increasing in
    P_d. The soft minimum lies in [min H - tau log(4 G), min H].
    """
    flat = H.reshape(H.shape[:-2] + (-1,))
    ok = jnp.isfinite(flat)
    any_ok = jnp.any(ok, axis=-1)
    safe = jnp.where(ok, flat, 0.0)
    h_min = jnp.min(jnp.where(ok, safe, jnp.inf), axis=-1)
    h_min = jnp.where(any_ok, h_min, 0.0)
    if tau is None:
        h = h_min
    else:
        ref = jax.lax.stop_gradient(h_min)  # the shift cancels exactly in value and gradient
        e = jnp.where(ok, jnp.exp(-(safe - ref[..., None]) / tau), 0.0)
        s = jnp.sum(e, axis=-1)
        h = ref - tau * jnp.log(jnp.where(any_ok, s, 1.0))
    return jnp.where(any_ok, h, _no_delivery_penalty(vp, P_d))


def _no_delivery_penalty(vp: VehicleParams, P_d):
    """H (W) of a demand no (mode, gear) can deliver: finite and increasing in P_d."""
    return P_PENALTY_W + 2.0 * jnp.maximum(P_d, 0.0) / vp.eta_e


class EcoTable(NamedTuple):
    """The minimised Hamiltonian tabulated over (speed, power) for fast eco-driving steps.

    H: (n_v, n_P) W, the soft (or hard) minimum over modes and gears of `mode_gear_split`'s H
    at speeds v0 + i dv and powers P0 + j dP; P_hi: () W, above which nothing can deliver the
    demand (P_PENALTY_W + 2 P / eta_e is used there, as `soft_min_hamiltonian` does).
    Below P0 the table is constant in P (the motor and the engine brake are saturated, the
    service brakes take the rest), so powers are clamped there.
    """

    H: Any
    v0: Any
    dv: Any
    P0: Any
    dP: Any
    P_hi: Any


TABLE_SIZE = (160, 384)  # default (speeds, powers) of an `EcoTable`


def eco_table(vp: VehicleParams, lam_b, v_top, tau=None, n_v: int = 160, n_P: int = 384):
    """`EcoTable` of ONE vehicle at costate lam_b for speeds V_CRAWL/2 .. v_top (m/s).

    n_v, n_P static; vp, lam_b, v_top, tau arrays (jit/vmap-able). The power range runs from
    -(P_m_max + engine-brake power) to the engine's full-load power plus P_m_max (5 % margins).
    """
    dtype = jnp.result_type(v_top, vp.mass, float)
    _, p_max = pt.engine_power_limits(vp, vp.te_max_w)
    p_brake, _ = pt.engine_power_limits(vp, vp.te_min_w)
    P_hi = 1.05 * (jnp.max(p_max) + vp.pm_max * vp.has_motor)
    P0 = -1.05 * (vp.pm_max * vp.has_motor - jnp.min(p_brake))
    v0 = jnp.asarray(0.5 * V_CRAWL, dtype)
    dv = (jnp.asarray(v_top, dtype) - v0) / (n_v - 1)
    dP = (P_hi - P0) / (n_P - 1)
    vs = v0 + dv * jnp.arange(n_v, dtype=dtype)
    Ps = P0 + dP * jnp.arange(n_P, dtype=dtype)
    lam = jnp.asarray(lam_b, dtype)

    def row(v):
        H = jax.vmap(mode_gear_split, in_axes=(None, 0, None, None))(vp, Ps, v, lam).H
        return soft_min_hamiltonian(H, Ps, vp, tau)

    H = jax.lax.map(row, vs)
    return EcoTable(H=H, v0=v0, dv=dv, P0=P0, dP=dP, P_hi=P_hi)


def table_hamiltonian(tab: EcoTable, vp: VehicleParams, P_d, v):
    """Bilinear interpolation of an `EcoTable` at (P_d, v) (arrays of one shape) -> H (W)."""
    n_v, n_P = tab.H.shape
    x = jnp.clip((v - tab.v0) / tab.dv, 0.0, n_v - 1.0)
    y = jnp.clip((P_d - tab.P0) / tab.dP, 0.0, n_P - 1.0)
    i = jnp.clip(jnp.floor(x).astype(jnp.int32), 0, n_v - 2)
    j = jnp.clip(jnp.floor(y).astype(jnp.int32), 0, n_P - 2)
    fx, fy = x - i, y - j
    h = ((1 - fx) * ((1 - fy) * tab.H[i, j] + fy * tab.H[i, j + 1])
         + fx * ((1 - fy) * tab.H[i + 1, j] + fy * tab.H[i + 1, j + 1]))
    return jnp.where(P_d > tab.P_hi, _no_delivery_penalty(vp, P_d), h)


def _cell_model(route: Route, vp: VehicleParams, v):
    """(P_d, v_mean, dt, valid) per cell, (N-1,) each, for node speeds v (see `eco_cells`)."""
    grade = jnp.asarray(route.grade)
    dtype = grade.dtype
    mask = jnp.asarray(route.mask)
    ds = jnp.asarray(route.ds, dtype)
    v = jnp.where(mask, jnp.asarray(v, dtype), 0.0)
    vi, vn = v[:-1], v[1:]
    vsum = jnp.maximum(vi + vn, V_CRAWL)
    dt = 2.0 * ds / vsum
    dke = 0.5 * vp.mass * (vn * vn - vi * vi)
    return (dke + _cell_work(route, vp, v)) / dt, 0.5 * vsum, dt, mask[1:]


def _cells(P_d, v_mean, dt, valid, h) -> EcoCells:
    return EcoCells(P_d=P_d, v_mean=v_mean, dt=jnp.where(valid, dt, 0.0), H=h,
                    energy=jnp.where(valid, h * dt, 0.0), valid=valid)


def eco_cells(route: Route, vp: VehicleParams, v, lam_b, tau=None, table=None) -> EcoCells:
    """The eco-driving cell model for node speeds v: (N,) m/s (ONE route, ONE vehicle).

    Within cell i the acceleration is constant, a = (v_i+1^2 - v_i^2) / (2 ds), the cell takes
    dt = 2 ds / (v_i + v_i+1) (the sum floored at V_CRAWL, as `profile_from_speed`), and the mean
    driveline power is the exact work over the cell divided by dt, as `resample` computes it:
    P_d = (0.5 m (v_i+1^2 - v_i^2) + int F_0 ds) / dt, int F_0 ds = (k_air (v_i^2 + v_i+1^2) / 2
    + F_roll + F_grade) ds (`powertrain.road_load`, v^2 linear in s). The cell's Hamiltonian is
    the (soft, tau in W; hard for None) minimum over modes and gears of Level 1's
    `mode_gear_split(vp, P_d, v_mean, lam_b).H` at the mean speed v_mean = ds / dt, or, with
    an `EcoTable` `table` (built at lam_b and tau), its bilinear interpolation (fast).
    """
    P_d, v_mean, dt, valid = _cell_model(route, vp, v)
    if table is None:
        h = soft_min_hamiltonian(_cell_hamiltonians(vp, P_d, v_mean, lam_b), P_d, vp, tau)
    else:
        h = table_hamiltonian(table, vp, P_d, v_mean)
    return _cells(P_d, v_mean, dt, valid, h)


def _cell_hamiltonians(vp, P_d, v_mean, lam_b):
    """(N-1, 4, G) Level 1's H of every mode and gear at each cell's mean power and speed."""
    lam = jnp.asarray(lam_b, P_d.dtype)
    return jax.vmap(mode_gear_split, in_axes=(None, 0, 0, None))(vp, P_d, v_mean, lam).H


def _soft_and_exact(route, vp, v, lam_b, tau):
    """(soft, exact) `EcoCells` of node speeds v from one evaluation of the (mode, gear) table."""
    P_d, v_mean, dt, valid = _cell_model(route, vp, v)
    H_tab = _cell_hamiltonians(vp, P_d, v_mean, lam_b)
    soft = soft_min_hamiltonian(H_tab, P_d, vp, tau)
    hard = soft_min_hamiltonian(H_tab, P_d, vp, None)
    return _cells(P_d, v_mean, dt, valid, soft), _cells(P_d, v_mean, dt, valid, hard)


def _stop_time(route: Route, dtype):
    return jnp.sum(jnp.where(jnp.asarray(route.mask), jnp.asarray(route.stop, dtype), 0.0))


def eco_cost(route: Route, vp: VehicleParams, v, lambda_t, lam_b, tau, table=None):
    """Surrogate eco-driving objective (J) of node speeds v: (N,) m/s; returns ().

    sum over cells of H dt + lambda_t x trip time (cell times plus the stops, a constant), with
    H the soft minimum (temperature tau, W) over modes and gears of Level 1's Hamiltonian
    H = P_f - lambda_b P_bi at the cell's mean power (see `eco_cells`). lambda_t: J/s (>= 0),
    the price of a second; lam_b: Level 2's battery costate (< 0). Differentiable in v.
    table: an `EcoTable` at (lam_b, tau) to interpolate H from instead (see `eco_cells`).
    """
    c = eco_cells(route, vp, v, lam_b, tau, table)
    dtype = c.dt.dtype
    time = jnp.sum(c.dt) + _stop_time(route, dtype)
    return jnp.sum(c.energy) + jnp.asarray(lambda_t, dtype) * time


def eco_cost_exact(route: Route, vp: VehicleParams, v, lambda_t, lam_b):
    """`eco_cost` with the exact minimum over modes and gears (tau -> 0); returns () J."""
    return eco_cost(route, vp, v, lambda_t, lam_b, None)


def speed_bounds(route: Route, vp: VehicleParams, w_pred=None, overspeed=0.0):
    """Bounds of the eco-driving speeds: (lo, hi, level3), lo, hi: (N,) m/s, level3: Profile.

    hi is Level 3's predicted speed (vmax, v0, traction forward, comfort braking backward, the
    start and end conditions) with the cruise speed v0 raised by ``overspeed`` (m/s, >= 0)
    where the route allows v0 (vmax >= v0): the band a predictive cruise control may use above
    its set speed, to regain on a descent the time it gave up before a crest; lower limits
    stay. With overspeed 0 (the default) hi is Level 3's own profile, and at Level 3's trip
    time the optimum can only be Level 3's. lo is 0 at stops, min(V_CRAWL, hi) elsewhere. The
    first and the last node are fixed to Level 3's own speed (lo = hi: standstill at a stop, v0
    for a flying start or a free end), so the kinetic energy at both ends, and the energy
    balance against Level 3, are the same (a free end left open would be slowed down for free).
    Padding: 0.
    """
    prof = velocity_profile(route, vp, w_pred)
    mask, _, _, _, floor = _limits(route, vp)
    vmax = jnp.asarray(route.vmax, prof.v.dtype)
    band = jnp.asarray(overspeed, prof.v.dtype)
    env = velocity_profile(route._replace(vmax=jnp.where(vmax >= vp.v_cruise, vmax + band, vmax)),
                           vp._replace(v_cruise=vp.v_cruise + band), w_pred)
    ends = last_node(mask) | (jnp.arange(mask.shape[0]) == 0)
    hi = jnp.where(ends, prof.v, jnp.maximum(env.v, prof.v))
    lo = jnp.where(mask, jnp.minimum(floor, hi), 0.0)
    lo = jnp.where(ends, hi, lo)
    return lo, hi, prof


def acceleration_limits(route: Route, vp: VehicleParams, v, w_pred=None):
    """Acceleration a and its limits per cell: (a, a_hi, a_lo), each (N-1,) m/s^2.

    a = (v_i+1^2 - v_i^2) / (2 ds); a_hi = forward_acceleration(vp, v_i, grade_i, w_i) (full
    traction of the engine at w_pred behind a CVT, capped at a_max, as Level 3's forward pass);
    a_lo = -vp.a_min (comfort braking; a_min is a positive number).
    """
    grade = jnp.asarray(route.grade)
    dtype = grade.dtype
    N = grade.shape[-1]
    ds = jnp.asarray(route.ds, dtype)
    w = jnp.broadcast_to(jnp.asarray(vp.w_pred if w_pred is None else w_pred, dtype), (N,))
    a = (v[1:] ** 2 - v[:-1] ** 2) / (2.0 * ds)
    a_hi = forward_acceleration(vp, v[:-1], grade[:-1], w[:-1])
    a_lo = jnp.broadcast_to(-jnp.asarray(vp.a_min, dtype), a.shape)
    return a, a_hi, a_lo


def acceleration_violation(route: Route, vp: VehicleParams, v, w_pred=None):
    """How far each cell breaks the acceleration limits: (N-1,) m/s^2, >= 0 (0 on padding)."""
    a, a_hi, a_lo = acceleration_limits(route, vp, v, w_pred)
    viol = jnp.maximum(a - a_hi, 0.0) + jnp.maximum(a_lo - a, 0.0)
    return jnp.where(jnp.asarray(route.mask)[1:], viol, 0.0)


def eco_regulariser(route: Route, v, weight, eps=ACC_EPS):
    """Switching proxy (J): weight x the total variation of the acceleration along the route,
    sum over neighbouring cells of sqrt((a_i+1 - a_i)^2 + eps^2) - eps (smooth near 0).

    The surrogate has no switching costs; without this term its optimum rides the kinks of H
    (engine on/off) with a pulse-and-glide sawtooth of cell-scale period, each pulse a mode
    switch Level 1 and the plant pay for. weight: J per m/s^2 of acceleration change (about
    the cost of the mode switches one change brings, Appendix C); 0 switches it off.
    """
    grade = jnp.asarray(route.grade)
    mask = jnp.asarray(route.mask)
    ds = jnp.asarray(route.ds, grade.dtype)
    v = jnp.where(mask, v, 0.0)
    a = (v[1:] ** 2 - v[:-1] ** 2) / (2.0 * ds)
    both = mask[1:-1] & mask[2:]  # cells i and i + 1 on the route
    da = jnp.where(both, a[1:] - a[:-1], 0.0)
    return weight * jnp.sum(jnp.sqrt(da * da + eps * eps) - eps)


def restore_feasible(route: Route, vp: VehicleParams, v, w_pred=None):
    """The largest speeds below v: (N,) that meet the acceleration limits (m/s).

    Level 3's passes with v as the limit: forward v_i+1 <= sqrt(v_i^2 + 2 a_hi(v_i) ds), then
    backward v_i <= sqrt(v_i+1^2 + 2 a_min ds); the crawl floor and the stops are kept as in
    Level 3 (a profile the truck cannot drive above the floor stays flagged by Level 3's
    `feasible`). A profile that meets the limits is returned unchanged.
    """
    grade = jnp.asarray(route.grade)
    dtype = grade.dtype
    N = grade.shape[-1]
    mask, ds, _, _, floor = _limits(route, vp)
    w = jnp.broadcast_to(jnp.asarray(vp.w_pred if w_pred is None else w_pred, dtype), (N,))
    v = jnp.where(mask, jnp.asarray(v, dtype), V_BIG)  # padding: no limit

    def fwd(vc, xs):
        g, w_i, lim_next, floor_next = xs
        a = forward_acceleration(vp, vc, g, w_i)
        v_next = jnp.minimum(lim_next, jnp.sqrt(jnp.maximum(vc * vc + 2.0 * a * ds, 0.0)))
        v_next = jnp.maximum(v_next, jnp.minimum(floor_next, lim_next))
        return v_next, v_next

    _, v_f = jax.lax.scan(fwd, v[0], (grade[:-1], w[:-1], v[1:], floor[1:]))
    v_f = jnp.concatenate([v[:1], v_f])

    def bwd(vc, xs):
        lim, cell = xs  # cell: node i + 1 is on the route (not padding)
        v_i = jnp.where(cell, jnp.minimum(lim, jnp.sqrt(vc * vc + 2.0 * vp.a_min * ds)), lim)
        return v_i, v_i

    _, v_b = jax.lax.scan(bwd, v_f[-1], (v_f[:-1], mask[1:]), reverse=True)
    return jnp.where(mask, jnp.concatenate([v_b, v_f[-1:]]), 0.0)


def _min_plus_scan(A, B, reverse=False):
    """x_i = min(A_i, x_prev + B_i) along the array (the previous element is i - 1, or i + 1
    when reverse), x_first = A_first (B_first is ignored): an associative scan of the maps
    x -> min(A, x + B), composed as min(A2, A1 + B2), B1 + B2."""
    B = B.at[-1 if reverse else 0].set(BIG_V2)

    def combine(e, f):  # e: earlier in scan order, f: later
        return jnp.minimum(f[0], e[0] + f[1]), e[1] + f[1]

    return jax.lax.associative_scan(combine, (A, B), reverse=reverse)[0]


def project_speeds(route: Route, vp: VehicleParams, v, v_ref, lo, hi, w_pred=None):
    """Feasible speeds near v: (N,) m/s, within [lo, hi] and the acceleration limits.

    In v^2 (linear in s at constant acceleration) with the traction limit taken at v_ref
    (c_i = 2 ds a_fwd(v_ref_i, grade_i); the previous iterate in `optimize_velocity`) and
    b = 2 ds a_min: first the lower bounds are made reachable (L_i = max(lo_i^2,
    L_i+1 - c_i) backward: the fixed end can be reached; L_i+1 = max(L_i+1, L_i - b) forward:
    the fixed start can brake to them), then v^2 is clipped to [L, hi^2] and lowered by
    Level 3's passes, x_i+1 = min(x_i+1, x_i + c_i) forward and x_i = min(x_i, x_i+1 + b)
    backward. All four are associative min-plus scans (parallel over the nodes). The result
    meets the limits of the traction at v_ref exactly; with v_ref = the result, exactly
    (`restore_feasible` is the sequential, exact counterpart that only lowers).
    """
    grade = jnp.asarray(route.grade)
    dtype = grade.dtype
    N = grade.shape[-1]
    mask = jnp.asarray(route.mask)
    ds = jnp.asarray(route.ds, dtype)
    w = jnp.broadcast_to(jnp.asarray(vp.w_pred if w_pred is None else w_pred, dtype), (N,))
    cell = mask[1:]
    c = jnp.where(cell, 2.0 * ds * forward_acceleration(vp, v_ref[:-1], grade[:-1], w[:-1]),
                  BIG_V2)
    b = jnp.where(cell, 2.0 * ds * vp.a_min, BIG_V2)
    pad = jnp.zeros(1, dtype)
    # lower bounds: reach the end (backward), brake from the start (forward); negated min-plus
    neg_L = _min_plus_scan(-(lo * lo), jnp.concatenate([c, pad]), reverse=True)
    neg_L = _min_plus_scan(neg_L, jnp.concatenate([pad, b]))
    L = -neg_L
    x = jnp.clip(jnp.clip(v, lo, hi) ** 2, L, hi * hi)
    x = _min_plus_scan(x, jnp.concatenate([pad, c]))
    x = _min_plus_scan(x, jnp.concatenate([b, pad]), reverse=True)
    x = jnp.maximum(x, jnp.minimum(L, hi * hi))
    return jnp.where(mask, jnp.sqrt(jnp.maximum(x, 0.0)), 0.0)


def cruise_speed(vp: VehicleParams, lambda_t, lam_b, tau, v_top, table=None, n: int = 256):
    """The constant speed (m/s) that minimises (H(F_0(v) v, v) + lambda_t) / v on a flat road,
    the cost per metre of cruising, over n speeds in [V_CRAWL, v_top] (H from `table` if given,
    else the soft minimum of `mode_gear_split` at tau); returns ()."""
    dtype = jnp.result_type(v_top, vp.mass, float)
    v = jnp.linspace(V_CRAWL, 1.0, n, dtype=dtype) * jnp.asarray(v_top, dtype)
    v = jnp.maximum(v, V_CRAWL)
    P_d = pt.road_load(vp, v, 0.0) * v
    if table is None:
        lam = jnp.asarray(lam_b, dtype)
        H = jax.vmap(mode_gear_split, in_axes=(None, 0, 0, None))(vp, P_d, v, lam).H
        h = soft_min_hamiltonian(H, P_d, vp, tau)
    else:
        h = table_hamiltonian(table, vp, P_d, v)
    return v[jnp.argmin((h + jnp.asarray(lambda_t, dtype)) / v)]


class _EcoSetup(NamedTuple):
    lo: Any
    hi: Any
    level3: Profile
    table: Any


def _eco_setup(route, vp, lam_b, tau, w_pred, table_size, overspeed=0.0) -> _EcoSetup:
    lo, hi, l3 = speed_bounds(route, vp, w_pred, overspeed)
    table = None
    if table_size is not None:
        n_v, n_P = table_size
        table = eco_table(vp, lam_b, jnp.maximum(jnp.max(hi) + 0.1, 1.0), tau, n_v, n_P)
    return _EcoSetup(lo, hi, l3, table)


def optimize_velocity(
    route: Route,
    vp: VehicleParams,
    lambda_t,
    lam_b,
    *,
    n_steps: int = N_STEPS,
    learning_rate=LEARNING_RATE,
    final_lr_ratio=FINAL_LR_RATIO,
    tau=TAU_W,
    switch_weight=SWITCH_WEIGHT,
    w_pred=None,
    overspeed=0.0,
    v_init=None,
    table_size: tuple[int, int] | None = TABLE_SIZE,
) -> EcoResult:
    """Eco-driving: node speeds that minimise fuel-equivalent energy + lambda_t x trip time.

    ONE route and ONE vehicle; pure, jit- and vmap-able. n_steps and table_size are static;
    lambda_t (J/s, >= 0, the price of a second), lam_b (Level 2's costate, < 0, about -2),
    learning_rate (m/s), final_lr_ratio, tau (W), switch_weight (J/(m/s^2)), w_pred (rad/s, ()
    or (N,); Level 3's engine speed), overspeed (m/s, `speed_bounds`), v_init ((N,) m/s or
    None) and the vehicle's leaves are arrays, so new values do not recompile.

    Problem: minimise `eco_cost(route, vp, v, lambda_t, lam_b, tau)` plus the switching proxy
    `eco_regulariser(route, v, switch_weight)` (J per m/s^2 of acceleration change; 0: the
    surrogate alone, whose optimum is a pulse-and-glide sawtooth that Level 1 and the plant
    pay in mode switches) over the node speeds v: (N,) subject to
      - bounds lo <= v <= hi (`speed_bounds`): hi = Level 3's own profile with its cruise
        speed raised by ``overspeed`` (m/s) where the route allows the cruise speed (0: the
        optimum is only ever slower than Level 3, where that pays), lo = 0 at stops and
        V_CRAWL elsewhere, the first and last node fixed to Level 3's;
      - acceleration limits per cell: -a_min <= (v_i+1^2 - v_i^2) / (2 ds) <= a_fwd(v_i, grade_i)
        (`acceleration_limits`; a_fwd as Level 3's forward pass).
    Method: the soft-minimised Hamiltonian is tabulated once over (speed, power) (`eco_table`,
    table_size = (n_v, n_P); None evaluates `mode_gear_split` per cell and step: exact, about
    100 x slower), then n_steps of projected Adam (optax) from Level 3's profile capped at the
    best cruise speed on a flat road (`cruise_speed`; or from v_init), the learning rate (m/s
    per step) decaying exponentially from learning_rate to final_lr_ratio x learning_rate
    (Adam's b2 = ADAM_B2, a short memory for a kinked objective). Every iterate is PROJECTED
    onto the constraints (`project_speeds`: the bounds, and the acceleration limits with the
    traction limit taken at the previous iterate), so no penalty is needed and the speeds can
    move as a whole (slowing down ahead of a crest along a climb at the traction limit). The
    iterate of least objective
    is kept; `restore_feasible` then removes what the lagged traction limit left
    (acc_violation: the largest violation before that, m/s^2). cost, cost_exact and energy_J
    are evaluated per cell with `mode_gear_split` (no table). If the objective is not finite,
    Level 3's profile is returned with status ECO_NONFINITE.

    Returns `EcoResult` (profile leaves (N,), history (n_steps,), the rest ()).
    """
    setup = _eco_setup(route, vp, lam_b, tau, w_pred, table_size, overspeed)
    return _eco_solve(route, vp, lambda_t, lam_b, setup, n_steps=n_steps,
                      learning_rate=learning_rate, final_lr_ratio=final_lr_ratio, tau=tau,
                      switch_weight=switch_weight, w_pred=w_pred, v_init=v_init)


def _eco_solve(route, vp, lambda_t, lam_b, setup: _EcoSetup, *, n_steps, learning_rate,
               final_lr_ratio, tau, switch_weight, w_pred, v_init) -> EcoResult:
    import optax  # noqa: PLC0415 (optax is only needed here)

    lo, hi, l3, table = setup
    dtype = hi.dtype
    lambda_t = jnp.asarray(lambda_t, dtype)
    tau = jnp.asarray(tau, dtype)

    sw = jnp.asarray(switch_weight, dtype)

    def loss(v):
        return eco_cost(route, vp, v, lambda_t, lam_b, tau, table) + eco_regulariser(route, v, sw)

    if v_init is None:  # Level 3's profile capped at the best cruise speed on a flat road
        v0 = jnp.minimum(hi, cruise_speed(vp, lambda_t, lam_b, tau, jnp.max(hi), table))
    else:
        v0 = jnp.asarray(v_init, dtype)
    v0 = project_speeds(route, vp, v0, hi, lo, hi, w_pred)

    def projected(v, g):  # the gradient without the components the bounds block
        return jnp.where(((v <= lo) & (g > 0)) | ((v >= hi) & (g < 0)), 0.0, g)

    lr0 = jnp.asarray(learning_rate, dtype)
    ratio = jnp.asarray(final_lr_ratio, dtype)

    def sched(count):  # exponential decay from lr0 to lr0 x ratio over n_steps (arrays)
        return lr0 * ratio ** (jnp.asarray(count, dtype) / max(n_steps, 1))

    opt = optax.adam(sched, b1=0.9, b2=ADAM_B2)
    vg = jax.value_and_grad(loss)

    def step(carry, _):
        v, st, best_v, best_f, best_g = carry
        f, g = vg(v)
        g = jnp.where(jnp.isfinite(g), g, 0.0)
        better = jnp.isfinite(f) & (f < best_f)
        best_v = jnp.where(better, v, best_v)
        best_f = jnp.where(better, f, best_f)
        best_g = jnp.where(better, jnp.linalg.norm(projected(v, g)), best_g)
        upd, st = opt.update(g, st, v)
        v = project_speeds(route, vp, v + upd, v, lo, hi, w_pred)
        return (v, st, best_v, best_f, best_g), f

    inf = jnp.asarray(jnp.inf, dtype)
    carry0 = (v0, opt.init(v0), v0, inf, inf)
    (v_last, _, best_v, best_f, best_g), hist = jax.lax.scan(step, carry0, None, length=n_steps)
    f_last, g_last = vg(v_last)
    last_better = jnp.isfinite(f_last) & (f_last < best_f)
    v_opt = jnp.where(last_better, v_last, best_v)
    g_norm = jnp.where(last_better, jnp.linalg.norm(projected(v_last, g_last)), best_g)
    f_opt = jnp.minimum(f_last, best_f)
    finite = jnp.isfinite(f_opt) & jnp.all(jnp.isfinite(v_opt))
    v_opt = jnp.where(finite, v_opt, hi)
    acc_viol = jnp.max(acceleration_violation(route, vp, v_opt, w_pred))
    v_ret = restore_feasible(route, vp, v_opt, w_pred)
    prof = profile_from_speed(route, vp, v_ret, l3.v_fwd, l3.v_bwd, l3.feasible)
    soft, hard = _soft_and_exact(route, vp, v_ret, lam_b, tau)
    energy = jnp.sum(hard.energy)
    status = jnp.where(l3.feasible, ECO_OK, ECO_STALL) | jnp.where(finite, 0, ECO_NONFINITE)
    return EcoResult(
        profile=prof,
        v_level3=l3.v,
        v_upper=hi,
        cost=jnp.sum(soft.energy) + lambda_t * prof.trip_time,
        cost_exact=energy + lambda_t * prof.trip_time,
        regulariser=eco_regulariser(route, v_ret, sw),
        energy_J=energy,
        trip_time=prof.trip_time,
        lambda_t=lambda_t,
        acc_violation=acc_viol,
        grad_norm=g_norm,
        history=hist,
        status=status.astype(jnp.int32),
    )


def match_trip_time(
    route: Route,
    vp: VehicleParams,
    target_trip_time,
    lam_b,
    *,
    n_bisect: int = N_BISECT,
    n_steps: int = N_STEPS,
    learning_rate=LEARNING_RATE,
    final_lr_ratio=FINAL_LR_RATIO,
    tau=TAU_W,
    switch_weight=SWITCH_WEIGHT,
    w_pred=None,
    overspeed=0.0,
    lambda_t_range=LAMBDA_T_RANGE,
    table_size: tuple[int, int] | None = TABLE_SIZE,
):
    """The time price lambda_t (J/s) whose eco-driving optimum takes target_trip_time (s).

    ONE route and ONE vehicle; pure, jit- and vmap-able; n_bisect, n_steps, table_size static.
    Bisection on log(lambda_t) over lambda_t_range = (lo, hi) J/s (the optimised trip time
    decreases as lambda_t grows), n_bisect steps, each a full `optimize_velocity` from Level 3's
    profile (the table is built once; the other keywords as `optimize_velocity`); the
    evaluated lambda_t whose trip time is closest to the
    target is returned, so (lambda_t, result) is what `optimize_velocity(..., lambda_t)` gives.
    Returns (lambda_t: () J/s, `EcoResult`). status flags: ECO_TARGET_FAST when the target is
    below the fastest trip found (no profile under Level 3's envelope is that fast; Level 3's
    own trip time is the limit), ECO_TARGET_SLOW when it is above the slowest (lambda_t at the
    bottom of the range), ECO_TARGET_MISSED when the trip time is off by more than
    MATCH_RTOL (0.5 %) for another reason (a jump of the trip time in lambda_t across the
    target: a non-convex problem; `target_flags`).
    """
    setup = _eco_setup(route, vp, lam_b, tau, w_pred, table_size, overspeed)
    dtype = setup.hi.dtype
    target = jnp.asarray(target_trip_time, dtype)
    u_lo = jnp.log(jnp.asarray(lambda_t_range[0], dtype))
    u_hi = jnp.log(jnp.asarray(lambda_t_range[1], dtype))

    def solve(lt):
        return _eco_solve(route, vp, lt, lam_b, setup, n_steps=n_steps,
                          learning_rate=learning_rate, final_lr_ratio=final_lr_ratio, tau=tau,
                          switch_weight=switch_weight, w_pred=w_pred, v_init=None)

    def body(carry, _):
        lo, hi, best, best_err = carry
        mid = 0.5 * (lo + hi)
        res = solve(jnp.exp(mid))
        slow = res.trip_time > target  # too slow: a second must cost more
        lo = jnp.where(slow, mid, lo)
        hi = jnp.where(slow, hi, mid)
        err = jnp.abs(res.trip_time - target)
        better = err < best_err
        best = jax.tree_util.tree_map(lambda a, b: jnp.where(better, a, b), res, best)
        return (lo, hi, best, jnp.minimum(err, best_err)), None

    first = solve(jnp.exp(0.5 * (u_lo + u_hi)))
    err0 = jnp.abs(first.trip_time - target)
    slow0 = first.trip_time > target
    lo = jnp.where(slow0, 0.5 * (u_lo + u_hi), u_lo)
    hi = jnp.where(slow0, u_hi, 0.5 * (u_lo + u_hi))
    (lo, hi, best, _), _ = jax.lax.scan(body, (lo, hi, first, err0), None,
                                        length=max(n_bisect - 1, 0))
    flags = target_flags((best.trip_time - target) / target, lo <= u_lo, hi >= u_hi)
    best = best._replace(status=(best.status | flags).astype(jnp.int32))
    return best.lambda_t, best


def target_flags(rel, all_fast, all_slow):
    """`match_trip_time`'s status flags from the best trip's relative error rel (its trip
    time minus the target, over the target) and whether every lambda_t the bisection tried
    gave a trip faster (all_fast: its bracket's low end never moved) or slower (all_slow: its
    high end never moved) than the target: ECO_TARGET_FAST where the best is too slow and so
    was every price, up to the range's top (the target is beyond Level 3's envelope),
    ECO_TARGET_SLOW where the best is too fast and so was every price, ECO_TARGET_MISSED where
    it misses by more than MATCH_RTOL otherwise: the trip time jumps across the target as
    lambda_t moves (on the short track at 20 t at 1.5 times Level 3's trip: 232.4 s at 3576
    J/s, 213.4 s at 3911, where the target was within reach and the run said too fast)."""
    fast = (rel > MATCH_RTOL) & all_slow
    slow = (rel < -MATCH_RTOL) & all_fast
    missed = (jnp.abs(rel) > MATCH_RTOL) & ~fast & ~slow
    return (jnp.where(fast, ECO_TARGET_FAST, 0) | jnp.where(slow, ECO_TARGET_SLOW, 0)
            | jnp.where(missed, ECO_TARGET_MISSED, 0))


# ----------------------------------------------------------------------------- batched
def _optimize_batch(routes, vehicles, lambda_t, lam_b, w, learning_rate, final_lr_ratio, tau,
                    switch_weight, overspeed, n_steps, table_size):
    TRACES["optimize_velocity_batch"] += 1

    def one(route, vp, lt, lb, w_i):
        return optimize_velocity(route, vp, lt, lb, n_steps=n_steps, learning_rate=learning_rate,
                                 final_lr_ratio=final_lr_ratio, tau=tau,
                                 switch_weight=switch_weight, w_pred=w_i, overspeed=overspeed,
                                 table_size=table_size)

    return jax.vmap(one)(routes, vehicles, lambda_t, lam_b, w)


_optimize_vmap = jit(_optimize_batch, static_argnames=("n_steps", "table_size"))


def optimize_velocity_batch(
    routes: Route | Sequence[Route],
    vehicles: VehicleParams | Sequence[VehicleParams],
    lambda_t,
    lam_b,
    *,
    n_steps: int = N_STEPS,
    learning_rate=LEARNING_RATE,
    final_lr_ratio=FINAL_LR_RATIO,
    tau=TAU_W,
    switch_weight=SWITCH_WEIGHT,
    w_pred=None,
    overspeed=0.0,
    table_size: tuple[int, int] | None = TABLE_SIZE,
) -> EcoResult:
    """`optimize_velocity` for a batch through one jitted `vmap`; equals a loop of single calls.

    routes: a list of `Route`s (padded with `pad_routes`) or a padded batch (leaves (B, N));
    vehicles: a list or stacked batch of B vehicles, or one vehicle; a single route with a batch
    of vehicles is accepted too (pairing as `predict_batch`: member b is route b with vehicle b;
    for every combination, repeat them). lambda_t, lam_b: () or (B,); w_pred: None (each
    vehicle's w_pred) or rad/s broadcastable to (B, N). New values of any of these reuse the
    compilation (TRACES["optimize_velocity_batch"] counts traces); learning_rate,
    final_lr_ratio, tau, switch_weight, overspeed: scalars shared by the batch. Returns
    `EcoResult` with a leading axis B.
    """
    routes, vehicles, w = _paired_batch(routes, vehicles, w_pred, "optimize_velocity_batch",
                                        "optimize_velocity")
    B = w.shape[0]
    dtype = w.dtype
    lt = np.broadcast_to(np.asarray(lambda_t, dtype), (B,))
    lb = np.broadcast_to(np.asarray(lam_b, dtype), (B,))
    for name, x in (("lambda_t", lt), ("lam_b", lb)):
        if not np.all(np.isfinite(x)):
            raise ValueError(f"optimize_velocity_batch: {name} must be finite (got {x})")
    if np.any(lt < 0):
        raise ValueError(f"optimize_velocity_batch: lambda_t must be >= 0 J/s (got {lt})")
    return _optimize_vmap(routes, vehicles, lt, lb, w, learning_rate, final_lr_ratio, tau,
                          switch_weight, overspeed, n_steps=n_steps, table_size=table_size)
