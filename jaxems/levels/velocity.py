"""Level 3: velocity prediction from the road ahead (paper section 6).

Three driving modes (maximum acceleration, minimum acceleration, cruise at v0) give the
predicted speed. On the distance grid of a `Route` (nodes s_i, cells of length ds):

    vlim_i   = min(vmax_i, v0), and 0 at stop nodes
    forward  v_{i+1} = min(vlim_{i+1}, sqrt(max(v_i^2 + 2 a ds, 0)))
             a       = min(a_fwd(v_i), a_fwd(v_pred)),  v_pred^2 = v_i^2 + 2 a_fwd(v_i) ds
             a_fwd(v) = min(a_max, (F_max(v) - F_0(v, grade_i)) / m)
             F_max(v) = min(P_e_max(w_pred) / v, T_e_peak r_G(1) r_d)
    backward v_i = min(vlim_i, sqrt(v_{i+1}^2 + 2 a_min ds))
    v_c      = min(v_forward, v_backward)

F_max is the tractive force of the engine alone (mode M_e) behind a continuously variable
gearbox holding the engine at w_pred (the paper's 1100 rpm, `VehicleParams.w_pred`), capped at
low speed by the peak engine torque in the lowest gear. The backward pass brakes at the comfort
limit a_min (service brakes always allowed). a_fwd decreases with v, so taking the smaller of
its values at the cell's start speed and at the predicted end speed keeps the traction force
within F_max over the whole cell (the driveline power stays within P_e_max while the forward pass
limits the speed). Both passes are `lax.scan`s in the v^2 form (the
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
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import powertrain as pt
from ..params import VehicleParams, stack_vehicles
from ..route import Route, pad_routes

V_CRAWL = 0.5  # m/s: lowest speed away from stops
V_BIG = 1.0e3  # m/s: "no limit" on padding nodes
STEP_BUCKET = 256  # time steps are rounded up to a multiple of this


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


def forward_acceleration(vp: VehicleParams, v, grade, w_pred):
    """a_fwd (m/s^2) = min(a_max, (F_max(v) - F_0(v, grade)) / m): mode 1, full traction."""
    f0 = pt.road_load(vp, v, grade)
    return jnp.minimum(vp.a_max, (traction_limit(vp, v, w_pred) - f0) / vp.mass)


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
    k_air = 0.5 * vp.c_w * vp.area * vp.rho
    f_grade = pt.road_load(vp, 0.0, grade)  # rolling + grade force per cell (N)
    cell_w = jnp.where(
        prof.mask[1:],
        (k_air * 0.5 * (v[:-1] ** 2 + v[1:] ** 2) + f_grade[:-1]) * ds,
        0.0,
    )
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
    v_end = jnp.sum(jnp.where(_last_node(prof.mask), prof.v, 0.0))
    s_t = jnp.where(done, prof.length, s_t)
    v_t = jnp.where(done, v_end, v_t)
    ds_k = jnp.diff(s_t)
    mask = ~done[:-1]
    v_mean = ds_k / dt
    a_mean = jnp.diff(v_t) / dt
    # mean gradient over the step from the cumulative rise (tan form, exact per cell)
    grade = jnp.asarray(route.grade, dtype)
    ds_r = jnp.asarray(route.ds, dtype)
    rise_nodes = jnp.concatenate([jnp.zeros(1, dtype), jnp.cumsum(grade[:-1] * ds_r)])
    rise_t = jnp.interp(s_t, prof.s, rise_nodes)
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


def _last_node(mask):
    """(N,) bool: True at the last valid node."""
    return mask & ~jnp.concatenate([mask[1:], jnp.zeros(1, bool)])


def _total_work(route: Route, vp: VehicleParams, prof: Profile):
    v = prof.v
    k_air = 0.5 * vp.c_w * vp.area * vp.rho
    grade = jnp.asarray(route.grade, v.dtype)
    f_grade = pt.road_load(vp, 0.0, grade)
    cell_w = (k_air * 0.5 * (v[:-1] ** 2 + v[1:] ** 2) + f_grade[:-1]) * route.ds
    return jnp.sum(jnp.where(prof.mask[1:], cell_w, 0.0))


# ----------------------------------------------------------------------------- host wrappers
_profile_jit = jax.jit(velocity_profile)
_resample_jit = jax.jit(resample, static_argnames=("n_steps",))
_profile_vmap = jax.jit(jax.vmap(velocity_profile, in_axes=(0, 0, 0)))


def _resample_batch(routes, vehicles, profs, dt, n_steps):
    return jax.vmap(lambda r, v, p: resample(r, v, p, dt, n_steps))(routes, vehicles, profs)


_resample_vmap = jax.jit(_resample_batch, static_argnames=("n_steps",))


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
    if not (isinstance(dt, int | float) and dt > 0 and math.isfinite(dt)):
        raise ValueError(f"dt must be a positive number of seconds (got {dt!r})")
    if np.ndim(route.ds) != 0 or np.ndim(vehicle.mass) != 0:
        raise ValueError("predict_velocity takes one route and one vehicle; use predict_batch")
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
    if not isinstance(routes, Route):
        routes = pad_routes(list(routes))
    if not isinstance(vehicles, VehicleParams):
        vehicles = stack_vehicles(list(vehicles))
    br = _batch_size(routes.ds)
    bv = _batch_size(vehicles.mass)
    if br is None and bv is None:
        raise ValueError(
            "predict_batch: neither routes nor vehicles are a batch; use predict_velocity"
        )
    if br is not None and bv is not None and br != bv:
        raise ValueError(f"predict_batch: {br} routes but {bv} vehicles (pair them one to one)")
    B = br if br is not None else bv
    if br is None:
        routes = Route(*(np.broadcast_to(np.asarray(x), (B, *np.shape(x))) for x in routes))
    if bv is None:
        vehicles = VehicleParams(
            *(np.broadcast_to(np.asarray(x), (B, *np.shape(x))) for x in vehicles)
        )
    N = np.shape(routes.grade)[-1]
    if w_pred is None:
        w = jnp.broadcast_to(jnp.asarray(vehicles.w_pred)[:, None], (B, N))
    else:
        w = jnp.broadcast_to(jnp.asarray(w_pred), (B, N))
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
