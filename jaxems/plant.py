"""Closed-loop plant simulation: the truck on the road under a controller (`lax.scan` over time).

The plant is the model of section 2 with what the EMS levels abstract away put back in:

- Mode and gear switches open the driveline for dt_M / dt_G (eq. 12): during that time there
  is no traction, the vehicle decelerates (or accelerates) under road load, and the switch
  costs the rotational energy needed to synchronise the new inertias (Appendix C.1), drawn from
  the battery through the motor (hybrid) or from fuel (conventional truck).
- The driver follows the Level 3 reference speed indexed by POSITION: after a disturbance it
  recovers the reference at the position it has reached (it does not catch up in time). The
  target speed for the end of a step is the planned speed one step ahead of where the plan is
  at the current position, so that launches from standstill proceed.
- Stops: the vehicle brakes to rest exactly at each stop position and stands for the stop's
  duration (open driveline, engine off in a hybrid, idling in a conventional truck). In the
  last second(s) of a stop (the longer open time) it engages the state the controller asks
  for, so that the switch's open driveline overlaps the standing time and the launch starts
  when the stop ends, as a driver engages the gear before setting off (not at the route's
  end, where the trip ends standing).
- Traction limits: when the active mode and gear cannot deliver the demanded power the vehicle
  falls short of the reference speed; service brakes take braking power the powertrain cannot.
- Battery limits: E_b never leaves [0, E_b_max]; the battery power is clipped and the engine
  covers the rest where it is connected.
- A low-level protection (Level 0) keeps the driveline in a state that runs at the current
  speed and can deliver the reference's own acceleration there (at least holding speed): the
  requested state where it can, else the current one, else the cheapest that can (for example
  the engine below idle after a slow climb, or a gear planned for the reference's speed when
  the vehicle is behind it after a switch).

Energy accounting: every step records fuel, battery energy, road work F_0 ds, kinetic energy and
each loss (engine, clutch slip, motor, battery, service brakes, synchronisation, idling), so that

    E_f + (E_b(t0) - E_b(tf)) = W_road + dE_kin + sum(losses)

closes (`energy_balance`). Longitudinal dynamics over a step with the road load F_0 evaluated
at the step's start: 1/2 m (v1^2 - v0^2) = (P_wheel dt) - F_0 ds,  ds = (v0 + v1)/2 dt.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from . import powertrain as pt
from . import switching as sw
from .levels import powersplit as ps
from .levels.velocity import V_CRAWL, last_node, node_rise
from .params import VehicleParams
from .shard import shortcut

MO = ps.MO


SEARCH_BLOCK = 64  # values per block of the plant's searches (`block_search`)


class Track(NamedTuple):
    """What the plant needs of the route and of the Level 3 reference (one route).

    ref_s, ref_v: (T+1,) planned position (m) and speed (m/s) at the step boundaries of the
    Level 3 time grid (ref_s non-decreasing; flat while standing). grid_s: (N,) node positions of
    the route's distance grid, grade: (N,) gradient (rise/run) from each node to the next,
    rise: (N,) height (m) of each node above the start (`velocity.node_rise`).
    stop_s, stop_t: (N+1,) position (m) and duration (s) of the first stop at or after each node
    (+inf / 0 where none follows). length: () route length (m). final_s: () position (m) from
    which the reference needs no more traction to the route's end (its final braking or
    coasting): from there the battery stores no more than the trip started with (+inf: no
    such cap). ref_c, grid_c: ref_s[::SEARCH_BLOCK], grid_s[::SEARCH_BLOCK], the first value of
    each block of the sorted positions (`block_search`); `with_search_blocks` sets them from
    ref_s and grid_s (again after either is replaced).
    """

    ref_s: Any
    ref_v: Any
    grid_s: Any
    grade: Any
    rise: Any
    stop_s: Any
    stop_t: Any
    length: Any
    final_s: Any
    ref_c: Any
    grid_c: Any

    def with_search_blocks(self) -> Track:
        """This track with ref_c and grid_c taken from its ref_s and grid_s."""
        return self._replace(ref_c=self.ref_s[::SEARCH_BLOCK], grid_c=self.grid_s[::SEARCH_BLOCK])


class Obs(NamedTuple):
    """What a controller observes at the start of a plant step (all scalars)."""

    k: Any  # plant step index
    j: Any  # index of the Level 3 step that contains the current position
    frac: Any  # fraction of that step's distance already covered
    s: Any  # position (m)
    v: Any  # speed (m/s)
    E_b: Any  # battery energy (J)
    mode: Any  # active mode (int)
    gear: Any  # active gear index (int)
    grade: Any  # mean road gradient over the distance the step is to cover (rise/run)
    P_req: Any  # power needed at the wheels to reach the target speed this step (W)
    v_op: Any  # speed at which the powertrain is evaluated this step (m/s)


class Command(NamedTuple):
    """A controller's decision: requested mode and gear, costate for the split, optional P_b.

    P_b = nan means: split with the Level 1 optimum at `lam`; a finite P_b (a plan's) is
    applied directly, clipped to what the active state and the battery allow. catch_up: with a
    finite P_b, whether the battery may also cover the power of recovering the reference speed
    after a switch (beyond the reference's own acceleration); if not, only the engine's headroom
    and the commanded motor power recover it, so the battery follows the plan's (in a state
    with the engine disconnected, M_m, the battery recovers it regardless), and, where
    level0_plan, Level 0 counts on no more motor power than the commanded in the engine's
    states (`protected_state`; else on what the battery holds).
    """

    mode: Any
    gear: Any
    lam: Any
    P_b: Any
    catch_up: Any = True
    level0_plan: Any = True


# A controller: (ctrl_params, ctrl_state, vehicle, obs) -> (ctrl_state, Command). Pure; the
# params pytree carries its arrays (plans, costates) so that runs batch with vmap.
Controller = Callable[[Any, Any, VehicleParams, Obs], tuple[Any, Command]]


class Totals(NamedTuple):
    """Energies (J) summed over the run; the terms of the energy balance."""

    fuel: Any
    road: Any  # work against road load, sum of F_0 ds (negative downhill)
    loss_engine: Any  # fuel energy not delivered at the crank, and engine braking
    loss_slip: Any  # launch clutch slip
    loss_motor: Any
    loss_battery: Any  # beta P_b^2
    loss_brake: Any  # service brakes
    loss_sync: Any  # synchronisation of inertias at switches (incl. conversion)
    mode_switches: Any
    gear_switches: Any
    max_shortfall: Any  # largest (reference speed at position - speed), m/s
    trip_time: Any  # s, time at which the route was completed (within its step)


class PlantState(NamedTuple):
    s: Any
    v: Any
    E_b: Any
    mode: Any
    gear: Any
    open_left: Any  # s of open driveline still to come (a switch in progress)
    dwell: Any  # s of standstill still to come at the current stop
    served: Any  # position (m) of the last stop served (-1 before the first)
    done: Any
    tot: Totals


class Trace(NamedTuple):
    """Per-step records (n_steps,), for plots and tests."""

    t: Any
    s: Any
    v: Any
    E_b: Any
    mode: Any
    gear: Any
    P_d: Any  # power at the wheels (W): powertrain plus service brakes
    P_e: Any
    P_m: Any
    P_b: Any
    P_f: Any
    P_brake: Any
    lam: Any
    v_ref: Any
    E_sync_b: Any  # synchronisation energy of the step's switch (J) from the battery
    E_sync_f: Any  # ... from fuel (the powers above are the step's mean without it)
    # what the totals count of the step's powers, in s: dt; at the trip's end dt times its
    # share (of its distance where it reaches the end moving, of its time where a final stop
    # holds the truck); 0 after the trip
    counted: Any


class PlantResult(NamedTuple):
    final: PlantState
    trace: Trace
    E_b0: Any


# ------------------------------------------------------------------------------ components
Ranges = ps.Ranges


def state_ranges(vp: VehicleParams, mode, gear, v) -> Ranges:
    """`powersplit.Ranges` of (mode, gear) at vehicle speed v (indices of one shape: leaves
    of that shape)."""
    w = pt.shaft_speeds(vp, v)[gear]
    return ps.component_ranges(vp, w, jnp.asarray(ps.ENGINE_CONNECTED)[mode],
                               jnp.asarray(ps.MOTOR_CONNECTED)[mode], gear == 0)


def all_ranges(vp: VehicleParams, v) -> Ranges:
    """`Ranges` of every state (mode x gear, flattened: leaves (4 n_gears,)) at speed v.

    Mapped over gears inside modes (as `powersplit.mode_gear_split`), so that what depends on
    the gear's speed alone (the capability curves) is evaluated once per gear, not per state.
    """
    w = pt.shaft_speeds(vp, v)  # (G,)
    launch = jnp.arange(w.shape[-1]) == 0
    per_gear = jax.vmap(ps.component_ranges, in_axes=(None, 0, None, None, 0))
    per_mode = jax.vmap(per_gear, in_axes=(None, None, 0, 0, None))
    r = per_mode(vp, w, jnp.asarray(ps.ENGINE_CONNECTED), jnp.asarray(ps.MOTOR_CONNECTED),
                 launch)
    return jax.tree.map(lambda x: x.reshape(-1), r)


def capacity(r: Ranges):
    """Largest power (W) each state of `all_ranges` delivers, -inf where it cannot run."""
    return jnp.where(r.ok, r.e_hi + r.m_lim, -jnp.inf)


def deliverable(vp: VehicleParams, r: Ranges, E_b, dt, pb_plan=jnp.inf):
    """Largest power (W) each state of `all_ranges` delivers for dt seconds, its motor limited
    by what the battery holds and, where the engine is connected and a plan holds the battery
    (pb_plan: () W, +inf where none does), to the motor power of the plan's battery power (at
    least 0, `plan_motor`); -inf where it cannot run."""
    pb_batt = _pb_of_pbi(vp, jnp.maximum(E_b, 0.0) / dt)
    m_hi = jnp.minimum(r.m_lim, r.pm0 + vp.eta_m * pb_batt)
    m_hi = jnp.where(r.ce & jnp.isfinite(pb_plan), jnp.minimum(m_hi, plan_motor(vp, r, pb_plan)),
                     m_hi)
    return jnp.where(r.ok, r.e_hi + m_hi, -jnp.inf)


def plan_motor(vp: VehicleParams, r: Ranges, pb_plan):
    """The motor power (W) a plan's battery power pb_plan allows in states r: its motor output,
    within [0, the motor's limit] (where pb_plan is not finite, 0)."""
    return jnp.clip(ps.pm_of_pb(vp, r, jnp.where(jnp.isfinite(pb_plan), pb_plan, 0.0)), 0.0,
                    r.m_lim)


def capable(vp: VehicleParams, r: Ranges, E_b, P_need, dt, pb_plan=jnp.inf):
    """Bool per state of `all_ranges`: it runs and delivers P_need for dt seconds (the motor's
    power is limited by what the battery holds, and by pb_plan: `deliverable`)."""
    return meets(deliverable(vp, r, E_b, dt, pb_plan), P_need)


def meets(give, P_need):
    """Bool: a deliverable power `give` (W) meets the need P_need, to 1e-6 of it."""
    return give >= P_need - 1e-6 * jnp.abs(P_need)


def _pb_of_pbi(vp, P_bi):
    """Terminal power P_b with internal power P_bi (inverse of eq. 7, the physical root),
    P_b = 2 P_bi / (1 + sqrt(1 + 4 beta P_bi)): the root (sqrt(1 + 4 beta P_bi) - 1) / (2 beta)
    without its cancellation, which in float32 lost power for a small beta (at 100 kW 3e-4 of
    it with beta 1e-9 / W, 40 % with 1e-12). P_bi below its least value -1 / (4 beta) gives
    that value's root, -1 / (2 beta)."""
    P_bi = jnp.maximum(P_bi, -0.25 / vp.beta)
    return 2.0 * P_bi / (1.0 + jnp.sqrt(jnp.maximum(1.0 + 4.0 * vp.beta * P_bi, 0.0)))


def sync_energy(vp: VehicleParams, mode0, gear0, mode1, gear1, v):
    """Synchronisation energy (J, >= 0) of the switch (mode0, gear0) -> (mode1, gear1) at speed
    v: the rise in rotational energy of each connected inertia, counted per component as in the
    switching costs (`switching.sync_energy`, Appendix C.1). A slipping engine in gear 1 turns
    at idle at least; a truck without a motor has no motor inertia to spin. Scalars."""
    w = pt.shaft_speeds(vp, v)
    w0, w1 = w[gear0], w[gear1]
    ce, cm = jnp.asarray(ps.ENGINE_CONNECTED), jnp.asarray(ps.MOTOR_CONNECTED)
    has_m = vp.has_motor > 0.5
    we0 = jnp.maximum(w0, jnp.where(gear0 == 0, vp.we_min, 0.0))
    we1 = jnp.maximum(w1, jnp.where(gear1 == 0, vp.we_min, 0.0))
    f = lambda x: jnp.asarray(x, w0.dtype)  # noqa: E731
    return (sw.sync_energy(vp, f(ce[mode0]), 0.0, we0, f(ce[mode1]), 0.0, we1)
            + sw.sync_energy(vp, 0.0, f(cm[mode0] & has_m), w0, 0.0, f(cm[mode1] & has_m), w1))


def path_sync_energy(vp: VehicleParams, mode, gear, v):
    """(T,) battery energy (J) a plan's switches draw for synchronisation, as the plant does:
    at step k the switch from step k-1's (mode, gear) to step k's at speed v_k, drawn through
    the motor (1 / eta_m); 0 at step 0 (a plan starts in its own first state) and for a truck
    without a motor (it pays in fuel). mode, gear, v: (T,)."""
    pm, pg, mode_sw, gear_sw = _path_switches(mode, gear)
    dU = jax.vmap(lambda a, b, c, d, x: sync_energy(vp, a, b, c, d, x))(pm, pg, mode, gear, v)
    return jnp.where((mode_sw | gear_sw) & (vp.has_motor > 0.5), dU / vp.eta_m, 0.0)


def _path_switches(mode, gear):
    """(previous mode, previous gear, mode switched, gear switched) at each step of a path,
    as the plant counts them (a gear change in the open mode is none). mode, gear: (T,)."""
    pm = jnp.concatenate([mode[:1], mode[:-1]])
    pg = jnp.concatenate([gear[:1], gear[:-1]])
    return pm, pg, mode != pm, (gear != pg) & (mode != MO)


def path_open_time(vp: VehicleParams, mode, gear):
    """(T,) seconds of open driveline (eq. 12) at each step of a plan's path (mode, gear: (T,)):
    dt_M at a mode switch, dt_G at a gear switch, the larger at both, as the plant opens it."""
    _, _, mode_sw, gear_sw = _path_switches(mode, gear)
    return _open_time(vp, mode_sw, gear_sw)


def _open_time(vp: VehicleParams, mode_sw, gear_sw):
    """Seconds the driveline opens for a mode and/or gear switch (flags, any shape): dt_M, dt_G,
    the larger at both (one event), 0 without a switch."""
    return jnp.maximum(jnp.where(mode_sw, vp.dt_M, 0.0), jnp.where(gear_sw, vp.dt_G, 0.0))


idle_fuel_power = ps.idle_fuel_power


def _stands(dwell, dt):
    """Whether a stop's remaining time dwell (s) still holds the vehicle for this step: the
    time runs from the arrival within a step and ends at the nearest step."""
    return dwell > 0.5 * dt


def block_search(a, a_c, v, side: str):
    """`jnp.searchsorted(a, v, side=side)` for a sorted (N,) and a scalar v, with a_c =
    a[::SEARCH_BLOCK]: the block starts are searched, then the one block (SEARCH_BLOCK values)
    that holds the answer. The plant searches its route and reference at every step; a binary
    search over the whole array touches log2(N) places spread over it, and on long routes, for
    batches under vmap, the plant's step then took up to twice as long per step as on a route
    a quarter as long (measured in docs/performance_history.md, "The plant's searches by blocks").
    With q block starts before v (side's sense), every value of the blocks before block q - 1
    is before v and every value from block q on is not, so the answer is in block q - 1; its
    window is clamped into the array (`dynamic_slice`), and the values it then also covers
    before that block are before v and counted by the window's search. Both searches compare
    v with every value searched at once (`method="compare_all"`: one fused kernel, where a
    binary search is a loop of a few kernels per halving, whose overhead in the plant's step
    was larger than its work); the blocks keep that to N / SEARCH_BLOCK + SEARCH_BLOCK
    comparisons instead of N."""
    N, B = a.shape[0], SEARCH_BLOCK
    if N <= B:
        return jnp.searchsorted(a, v, side=side, method="compare_all")
    q = jnp.searchsorted(a_c, v, side=side, method="compare_all")
    start = jnp.clip((q - 1) * B, 0, N - B)
    window = jax.lax.dynamic_slice_in_dim(a, start, B)
    return start + jnp.searchsorted(window, v, side=side, method="compare_all")


def at_or_past(s):
    """Position s (m) moved forward by a rounding tolerance, for what asks which step or node
    the vehicle has reached (the searches; whether it is past the last traction): a plant
    that follows the reference exactly reaches each step's end up to rounding, an ulp short
    or past, and counted an ulp short it asked for the plan's state one step late. Which side
    it landed on differed between compilations (the conventional truck on the short track,
    float64: 0.52 % more fuel on a GPU than on the CPU from one gear switch a step earlier).
    1e-6 m, or 8 ulps where that is more (float32 far along a route); nothing a vehicle drives
    in a step."""
    return s + jnp.maximum(1e-6, 8 * jnp.finfo(jnp.result_type(s)).eps * jnp.abs(s))


def _interp(x, xp, xp_c, fp):
    """`jnp.interp(x, xp, fp)` for a scalar x, its search by `block_search`."""
    return pt.interp_at(block_search(xp, xp_c, x, "right"), x, xp, fp)


def _mean_grade(track: Track, s, ds):
    """Mean gradient over [s, s + ds] within the route, exact per cell (the gradient at s where
    that stretch is shorter than 1 mm): the road work of a step does not depend on where its
    start falls against the gradient's changes."""
    s1 = jnp.minimum(s + ds, track.length)
    d = s1 - s
    r0 = block_search(track.grid_s, track.grid_c, s, "right")  # one search at s, for both
    h0 = pt.interp_at(r0, s, track.grid_s, track.rise)
    h1 = _interp(s1, track.grid_s, track.grid_c, track.rise)
    i = jnp.clip(r0 - 1, 0, track.grade.shape[0] - 1)
    far = d > 1e-3
    return jnp.where(far, (h1 - h0) / jnp.where(far, d, 1.0), track.grade[i])


def _ref_position(track: Track, s):
    """(j, frac): the Level 3 step containing position s and the fraction covered."""
    T = track.ref_s.shape[0] - 1
    # the number of step ends ref_s[1:] at or before s; counted on ref_s itself, because XLA
    # copies a slice ref_s[1:] inside the plant's loop at every step (T values a step: the
    # plant's time grew as T^2 on long routes)
    s_q = at_or_past(s)
    n_le = block_search(track.ref_s, track.ref_c, s_q, "right") - (track.ref_s[0] <= s_q)
    j = jnp.clip(n_le, 0, T - 1)
    ds = track.ref_s[j + 1] - track.ref_s[j]
    frac = jnp.clip(jnp.where(ds > 0, (s - track.ref_s[j]) / jnp.where(ds > 0, ds, 1.0), 0.0),
                    0.0, 1.0)
    return j, frac


def _ref_speed(track: Track, j, frac):
    T = track.ref_s.shape[0] - 1
    a = track.ref_v[jnp.clip(j, 0, T)]
    b = track.ref_v[jnp.clip(j + 1, 0, T)]
    return a + frac * (b - a)


def _motion_short(vp, v0, F0, P_wheel, dt):
    """(v1, ds): end speed and distance when the wheels deliver P_wheel for dt against road
    load F0, at constant deceleration. Where even v1 = 0 leaves the energy equation short (a
    climb the driveline cannot hold, or holds open), the truck stops within the step, after
    t_s = m v0^2 / (F0 v0 - 2 P_wheel) and v0 t_s / 2, and stands: running the whole step to
    rest would count road work on distance never driven, which the service brakes then paid
    in (positive P_brake, a negative brake loss, on a 30 % climb)."""
    a = 0.5 * vp.mass
    b = 0.5 * F0 * dt
    c = -(0.5 * vp.mass * v0 * v0 - b * v0 + P_wheel * dt)
    disc = b * b - 4.0 * a * c
    root = (-b + jnp.sqrt(jnp.maximum(disc, 0.0))) / (2.0 * a)
    moving = (disc > 0) & (root > 0)
    den = F0 * v0 - 2.0 * P_wheel  # > 0 wherever the truck stops while moving
    t_s = jnp.where(den > 0, jnp.clip(vp.mass * v0 * v0 / jnp.where(den > 0, den, 1.0), 0.0, dt),
                    dt)
    return jnp.where(moving, root, 0.0), jnp.where(moving, 0.5 * (v0 + root) * dt, 0.5 * v0 * t_s)


def protected_state(vp: VehicleParams, E_b, P_need, v_op, v_after, lam, s_req, s_cur,
                    at_rest, pb_plan, dt):
    """Level 0 protection: the state (index mode * n_gears + gear) the driveline takes.

    The requested state s_req where it runs at v_op and delivers P_need (a switch opens the
    driveline: switched into, it must also at v_after, the speed left after the open time), or
    at rest (`requested_serves`); else, where s_cur still serves, s_cur (no hunting), but
    where the request is another gear in s_cur's mode that serves at v_op, kept out only by
    the speed its switch's open time takes, and v_op turns it at least at the engine's idle
    speed (not in a launch), the gear strictly between the two nearest the requested that
    serves after the switch, where one does (on a climb at 30 km/h the plan cruised in M_c in
    gear 10, which no upshift reaches there; the plant held gear 7, where its upshifts had
    fallen behind, though 8 and 9 served, and burnt 11 % more than the conventional truck,
    which held gear 9; a step across modes too moved Urban Delivery's multilevel run 3 % of
    the battery off its charge); else
    the requested mode in the gear of least H (at lam) that serves, else the state of least H
    that serves, else s_cur where it runs (not open) and delivers at least what any other
    state could at v_after, else the state of least H that serves at v_op, else the most
    capable. A state serves with its motor limited by the battery's energy and, in the
    engine's states, by pb_plan (W), the battery power of a plan that holds the battery (+inf
    where none does, `deliverable`). Every state is evaluated; the plant calls it only where
    the requested state does not serve (`shard.shortcut`). Scalars in, int32 () out."""
    n_g = vp.gear_ratio.shape[-1]
    keep, _ = requested_serves(vp, E_b, P_need, v_op, v_after, lam, s_req, s_cur, at_rest,
                               pb_plan, dt)
    r_now = all_ranges(vp, v_op)
    give_now = deliverable(vp, r_now, E_b, dt, pb_plan)
    give_after = deliverable(vp, all_ranges(vp, v_after), E_b, dt, pb_plan)
    ok_now = meets(give_now, P_need)
    ok_after = ok_now & meets(give_after, P_need)
    table = ps.mode_gear_split(vp, P_need, v_op, lam)
    Hf = jnp.where(table.feasible, table.H, jnp.inf).reshape(-1)
    best_after = jnp.argmin(jnp.where(ok_after, Hf, jnp.inf))
    best_now = jnp.argmin(jnp.where(ok_now, Hf, jnp.inf))
    # where no state serves after a switch, a switch delivers no more than its state can after
    # the open time: the current state stays where it runs and delivers at least that (on a
    # climb too steep to shift on, a downshift for power would stall the truck)
    others = jnp.arange(Hf.shape[0]) != s_cur
    stay = ((s_cur // n_g) != MO) & (give_now[s_cur] >= jnp.max(jnp.where(others, give_after,
                                                                             -jnp.inf)))
    best = jnp.where(jnp.any(ok_after), best_after,
                     jnp.where(stay, s_cur,
                               jnp.where(jnp.any(ok_now), best_now, jnp.argmax(capacity(r_now)))))
    same_mode = (jnp.arange(Hf.shape[0]) // n_g) == (s_req // n_g)
    in_mode = jnp.where(same_mode & ok_after, Hf, jnp.inf)
    alt = jnp.argmin(in_mode)
    gears = jnp.arange(Hf.shape[0]) % n_g
    g_cur, g_req = s_cur % n_g, s_req % n_g
    # not in a launch: at or above the speed at which the requested gear turns the engine at
    # idle (below it the greedy test controller's requests stepped the launch through gears)
    driving = pt.shaft_speeds(vp, v_op)[g_req] >= vp.we_min
    between = (driving & ok_now[s_req] & (s_cur // n_g == s_req // n_g) & same_mode & ok_after
               & ((gears - g_cur) * (g_req - gears) > 0))  # (S,)
    toward = jnp.argmin(jnp.where(between, jnp.abs(gears - g_req), n_g))
    held = jnp.where(between[toward], toward, s_cur)
    s_alt = jnp.where(ok_now[s_cur], held, jnp.where(jnp.isfinite(in_mode[alt]), alt, best))
    return jnp.where(keep, s_req, s_alt).astype(jnp.int32)


def requested_serves(vp: VehicleParams, E_b, P_need, v_op, v_after, lam, s_req, s_cur,
                     at_rest, pb_plan, dt):
    """(known, s_req): whether `protected_state` keeps the requested state, from that state's
    ranges alone (at rest, or it serves: at v_op, and at v_after where it is a switch). Where
    known is False the full evaluation decides (`shard.shortcut`)."""
    n_g = vp.gear_ratio.shape[-1]

    def serves(v):  # the requested state runs at speed v and delivers P_need
        return capable(vp, state_ranges(vp, s_req // n_g, s_req % n_g, v), E_b, P_need, dt,
                       pb_plan)

    ok_req = serves(v_op)
    req_ok = jnp.where(s_req == s_cur, ok_req, ok_req & serves(v_after))
    return req_ok | at_rest, jnp.asarray(s_req, jnp.int32)


ESCAPE_MARGIN = 1.6  # what a state taking over after a switch must deliver, over holding speed


def _top_speed(vp: VehicleParams, mode, gear):
    """Top speed (m/s) of (mode, gear): where a connected engine or motor reaches its largest
    speed; +inf in the open mode (and in the motor modes of a truck without a motor). Indices
    of one shape: that shape out."""
    ce = jnp.asarray(ps.ENGINE_CONNECTED)[mode]
    cm = jnp.asarray(ps.MOTOR_CONNECTED)[mode] & (vp.has_motor > 0.5)
    w_top = jnp.minimum(jnp.where(ce, vp.we_max, jnp.inf), jnp.where(cm, vp.wm_max, jnp.inf))
    return w_top / (jnp.asarray(vp.gear_ratio)[gear] * vp.r_d)


def held_top_speed(vp: VehicleParams, mode, gear, F0, E_b, dt):
    """The top speed (m/s) of state (mode, gear) where the truck could not leave it for a
    faster one: after the speed a switch's open second takes (road load F0 for dt_G), none of
    the next gear in M_c, M_e or M_m, or the same gear in M_m, would run with ESCAPE_MARGIN
    times the power of holding that speed (below its engine's idle, or short of the power, its
    motor limited by the battery's energy E_b); +inf where one would, and in the open mode.
    The plant does not accelerate past it: launched in gear 1 on a 30 % climb, a truck crawls
    up at gear 1's top speed instead of running past it, being switched into a stall and
    launching again. Scalars in, () out."""
    n_g = vp.gear_ratio.shape[-1]
    v_top = _top_speed(vp, mode, gear)  # +inf in the open mode: never held
    top = jnp.where(jnp.isfinite(v_top), v_top, 0.0)
    v_esc = jnp.maximum(top - jnp.maximum(F0, 0.0) * vp.dt_G / vp.mass, 0.1)
    up = jnp.minimum(gear + 1, n_g - 1)
    modes = jnp.asarray([ps.MC, ps.ME, ps.MM, ps.MM])
    gears = jnp.stack([up, up, up, gear])
    faster = _top_speed(vp, modes, gears) > top * (1.0 + 1e-9)
    give = deliverable(vp, state_ranges(vp, modes, gears, v_esc), E_b, dt)
    escapes = jnp.any(faster & (give >= ESCAPE_MARGIN * jnp.maximum(F0, 0.0) * v_esc))
    # a hair below the top, so that rounding keeps the engine within its speed range there
    return jnp.where(escapes, jnp.inf, v_top * (1.0 - 1e-5))


def speed_after_switch(vp: VehicleParams, v_op, F0):
    """The speed (m/s) Level 0 asks a state switched into to run at: v_op less what road load
    F0 (N, where it resists) takes in the longer open time (a mode and gear switch), at least
    0.1. Broadcasts."""
    return jnp.maximum(v_op - jnp.maximum(F0, 0.0) * _open_time(vp, True, True) / vp.mass, 0.1)


def protection(dt):
    """Level 0 as the plant's step calls it: `protected_state` where `requested_serves` does
    not already know the answer (`shard.shortcut`; dt: the step, s)."""
    return shortcut(functools.partial(requested_serves, dt=dt),
                    functools.partial(protected_state, dt=dt))


# ------------------------------------------------------------------------------ the step
def _step(vp: VehicleParams, track: Track, controller: Controller, dt, carry, k):
    st, cparams, cstate = carry
    z = jnp.zeros_like(st.v)
    s0, v0 = st.s, st.v
    j, frac = _ref_position(track, s0)
    v_ref_here = _ref_speed(track, j, frac)
    v_ref_next = _ref_speed(track, j + 1, frac)

    # --- target: follow the reference, stop exactly at the next stop, stand for its duration
    N = track.grid_s.shape[0]
    s_at = at_or_past(s0)  # the node reached, and below whether past the last traction
    i_node = jnp.clip(block_search(track.grid_s, track.grid_c, s_at, "right") - 1, 0, N - 1)
    i_next = jnp.where(track.stop_s[i_node] > st.served + 1e-6, i_node, i_node + 1)
    s_stop = track.stop_s[i_next]
    t_stop = track.stop_t[i_next]
    has_stop = jnp.isfinite(s_stop)
    d_stop = jnp.maximum(s_stop - s0, 0.0)
    standing = _stands(st.dwell, dt)
    # never below Level 3's crawl speed short of a stop or the end (a reference that rounds to
    # zero just before a stop must not leave the truck standing there)
    d_left = jnp.minimum(d_stop, jnp.maximum(track.length - s0, 0.0))
    v_tgt = jnp.where(standing, 0.0, jnp.maximum(v_ref_next, jnp.minimum(V_CRAWL, d_left / dt)))
    v_cap = jnp.maximum(2.0 * d_stop / dt - v0, 0.0)
    v1_tgt = jnp.minimum(jnp.minimum(v_tgt, v0 + vp.a_max * dt), v_cap)
    ds_tgt = jnp.minimum(0.5 * (v0 + v1_tgt) * dt, d_stop)
    # road load on the step's mean gradient, as Level 3 predicts it (the end of a step that is
    # short of its target lies a little back on the same stretch)
    grade = _mean_grade(track, s0, ds_tgt)
    F0 = pt.road_load(vp, v0, grade)
    # not past the top speed of a gear the truck cannot leave for a faster state
    # (`held_top_speed`; never slower than it runs: the cap limits acceleration only)
    v_held = jnp.maximum(held_top_speed(vp, st.mode, st.gear, F0, st.E_b, dt), v0)
    v1_tgt = jnp.minimum(v1_tgt, v_held)
    ds_tgt = jnp.minimum(0.5 * (v0 + v1_tgt) * dt, d_stop)
    P_req = (0.5 * vp.mass * (v1_tgt**2 - v0**2) + F0 * ds_tgt) / dt
    # the powertrain runs at the step's start speed (at the mean target speed when launching)
    v_op = jnp.where(v0 > 0, v0, ds_tgt / dt)

    obs = Obs(k=k, j=j, frac=frac, s=s0, v=v0, E_b=st.E_b, mode=st.mode, gear=st.gear,
              grade=grade, P_req=P_req, v_op=v_op)
    cstate, cmd = controller(cparams, cstate, vp, obs)
    lam = jnp.asarray(cmd.lam, dtype=v0.dtype)

    # --- state transitions: standstill forces the open mode, except in the stop's last
    # second(s), when the launch state is engaged; Level 0 protection keeps the driveline in a
    # state that can run at this speed and deliver what is needed
    at_rest = standing | ((v0 <= 0) & (v1_tgt <= 0))
    t_open = _open_time(vp, True, True)  # the longer open time (a mode and gear switch)
    # (not at the route's end: there the trip ends standing)
    engage = (standing & ~_stands(st.dwell - jnp.maximum(t_open, dt), dt)
              & (s0 < track.length - 1e-3))
    n_g = vp.gear_ratio.shape[-1]
    s_cur = st.mode * n_g + st.gear
    s_cmd = cmd.mode * n_g + cmd.gear
    s_req = jnp.where(at_rest & ~engage, MO * n_g + st.gear, s_cmd)
    # what must be delivered: the full demand from standstill; moving, the force of the
    # reference's own acceleration here (not the catch-up after a switch), at least holding
    # speed (a state that only holds speed leaves the vehicle behind the reference for good)
    a_ref = (v_ref_next - v_ref_here) / dt
    P_follow = jnp.maximum(F0 + jnp.maximum(vp.mass * a_ref, 0.0), 0.0) * v0
    P_need = jnp.where(v0 > 0, jnp.minimum(P_req, P_follow), P_req)
    # a switch opens the driveline: the state switched into must still run after the speed
    # lost meanwhile
    v_after = speed_after_switch(vp, v_op, F0)
    # a plan that holds the battery (below its energy, `Command.catch_up`) allows the motor
    # its planned power in the engine's states, not the battery's: a state serves with that
    planned = jnp.isfinite(cmd.P_b)
    limit_b = planned & ~jnp.asarray(cmd.catch_up, bool)
    pb_plan = jnp.where(limit_b & jnp.asarray(cmd.level0_plan, bool), cmd.P_b,
                        jnp.inf).astype(v0.dtype)
    s_new = protection(dt)(vp, st.E_b, P_need, v_op, v_after, lam, s_req, s_cur, at_rest,
                           pb_plan)
    req_mode = (s_new // n_g).astype(st.mode.dtype)
    req_gear = (s_new % n_g).astype(st.gear.dtype)

    mode_sw = (req_mode != st.mode) & ~st.done
    gear_sw = (req_gear != st.gear) & ~st.done & (req_mode != MO)
    new_open = _open_time(vp, mode_sw, gear_sw)
    open_left = jnp.maximum(st.open_left, new_open)
    f_open = jnp.clip(open_left / dt, 0.0, 1.0)
    mode = req_mode
    gear = jnp.where(req_mode == MO, st.gear, req_gear)
    # synchronisation energy of the new inertias (App. C.1): from the battery or from fuel
    dU = jnp.where(mode_sw | gear_sw, sync_energy(vp, st.mode, st.gear, mode, gear, v0), 0.0)
    sync_from_batt = (vp.has_motor > 0.5) & (st.E_b >= dU / vp.eta_m)
    E_sync_b = jnp.where(sync_from_batt, dU / vp.eta_m, 0.0)
    E_sync_f = jnp.where(sync_from_batt, 0.0, dU / vp.eta_e)

    # --- power split in the active state
    r = state_ranges(vp, mode, gear, v_op)
    traction = (1.0 - f_open) * r.ok
    cap_hi = traction * (r.e_hi + r.m_lim)
    P_dem = jnp.minimum(P_req, cap_hi)  # traction-limited demand (brakes take any excess)
    # a plan's battery power: recovering the reference after a switch on the engine's headroom
    # (and the commanded motor power) unless the controller lets the battery cover it; with
    # the engine disconnected (M_m) the battery is all there is, and it recovers the reference
    # (else the truck would hold the speed it has, behind the reference, until the plan's
    # next engine state)
    limit = limit_b & r.ce
    cap_plan = traction * (r.e_hi + plan_motor(vp, r, cmd.P_b))  # used only where limit
    P_dem = jnp.where(limit, jnp.minimum(P_dem, jnp.maximum(P_need, cap_plan)), P_dem)
    opt = ps.split_state(vp, P_dem, v_op, lam, mode, gear)
    P_b = jnp.where(planned, cmd.P_b, opt.P_b)
    # the motor never delivers what the service brakes would take again: at most the power
    # that, with the engine at its lowest, meets the step's requirement; braking, at least
    # what the requirement leaves after the engine's drag. A plan's step is not the plant's:
    # where the plant brakes and the plan's step still drives, or brakes less, the motor
    # recuperates the plant's braking (without this, on Urban Delivery at 20 t the plant drove
    # the motor against its service brakes on 49 steps, 0.71 MJ braked away, and regenerated
    # only the plan's braking at each braking onset: the plant fell 0.2-0.8 MJ behind its plan)
    P_b = jnp.minimum(P_b, ps.pb_engine_lowest(vp, r, P_req))
    P_b = jnp.where(traction > 0, P_b, 0.0)
    # battery power range of this state at this demand, and the battery's energy limits
    pb_lo = ps.pb_engine_highest(vp, r, P_dem)
    pb_hi = ps.pb_of_pm(vp, r, r.m_lim)
    E_avail = st.E_b - E_sync_b
    pb_hi = jnp.minimum(pb_hi, _pb_of_pbi(vp, E_avail / dt))
    # past the reference's last traction, charge sustaining is all the battery still serves:
    # it stores up to the energy the trip started with (never forced to discharge), the
    # service brakes take the rest
    E_ceil = jnp.where(s_at >= track.final_s,
                       jnp.maximum(vp.soc0 * vp.E_b_max, E_avail),
                       vp.E_b_max)
    pb_lo = jnp.maximum(pb_lo, _pb_of_pbi(vp, (E_avail - E_ceil) / dt))
    P_b = jnp.clip(P_b, jnp.minimum(pb_lo, pb_hi), pb_hi)
    P_m = ps.pm_of_pb(vp, r, P_b) * (traction > 0)
    P_b = jnp.where(traction > 0, P_b, 0.0)
    P_out = jnp.where(r.ce & (traction > 0), jnp.clip(P_dem - P_m, r.e_lo, r.e_hi), 0.0)
    P_p = P_out + P_m
    P_brake = jnp.minimum(P_req - P_p, 0.0)
    P_wheel = P_p + P_brake
    P_e = r.k * P_out
    P_f = jnp.where(r.ce & (traction > 0), jnp.maximum(P_e - r.pe0, 0.0) / vp.eta_e, 0.0)
    idle = (vp.has_motor < 0.5) & ((mode == MO) | (traction <= 0)) & ~st.done
    P_idle = jnp.where(idle, idle_fuel_power(vp), 0.0)

    # --- vehicle motion
    short = P_wheel < P_req - 1e-9 * (1.0 + jnp.abs(P_req))
    v1_s, ds_s = _motion_short(vp, v0, F0, P_wheel, dt)
    v1 = jnp.where(short, v1_s, v1_tgt)
    ds = jnp.where(short, ds_s, ds_tgt)
    P_wheel = jnp.where(short, (0.5 * vp.mass * (v1**2 - v0**2) + F0 * ds) / dt, P_wheel)
    # a step that reaches a stop ends at rest there, and the stop's time runs from its arrival.
    # One capped to end at the stop, where its target could not stop within it, reaches it
    # still rolling: the service brakes take that speed's energy at the step's end. (Before,
    # the next step braked the last 0.3 m/s or so away in a driving state: the conventional
    # truck on Urban Delivery switched from the open mode into M_e in gear 1 and back there,
    # 80 mode switches, now 54; and at the route's final stop the trip ended rolling, the
    # stop's time, which Level 3's trip counts, uncounted)
    arrived = has_stop & (d_stop - ds <= 1e-3) & ~standing
    P_wheel = jnp.where(arrived, P_wheel - 0.5 * vp.mass * v1 * v1 / dt, P_wheel)
    v1 = jnp.where(arrived, 0.0, v1)
    P_brake = P_wheel - P_p
    # braking to rest at constant deceleration reaches the stop 2 ds / v0 into the step (at
    # once when already at rest): the stop's time runs from there
    t_in = jnp.clip(jnp.where(v0 + v1 > 0, 2.0 * ds / jnp.maximum(v0 + v1, 1e-12), 0.0), 0.0, dt)
    dwell = jnp.where(arrived, jnp.maximum(t_stop - (dt - t_in), 0.0),
                      jnp.maximum(st.dwell - dt, 0.0))
    served = jnp.where(arrived, s_stop, st.served)
    s1 = jnp.where(arrived, s_stop, s0 + ds)
    finished = (s1 >= track.length - 1e-3) & ~_stands(dwell, dt)
    # the moment the trip ends, within its step: where the end is reached (at a stop, t_in;
    # else under the step's constant acceleration, 2 d / (v0 + v_d), v_d^2 = v0^2 + 2 a d)
    # and its stop's time, or the time a stop at the end still held the truck
    d_end = jnp.clip(track.length - s0, 0.0, ds)
    v_d = jnp.sqrt(jnp.maximum(v0 * v0 + 2.0 * (v1 - v0) / dt * d_end, 0.0))
    t_end = jnp.where(v0 + v_d > 0, 2.0 * d_end / jnp.maximum(v0 + v_d, 1e-12), 0.0)
    t_end = jnp.where(arrived, t_in + t_stop, jnp.clip(t_end, 0.0, dt))
    t_fin = k * dt + jnp.where(standing, st.dwell, t_end)

    # the step that ends the trip counts up to its end: where it reaches the end moving, the
    # share of its distance up to there (under its constant acceleration every energy of the
    # step, the road's work and the kinetic change, scales with the distance covered, so the
    # balance holds, and the truck ends at the end at its speed there), where a stop at the end
    # still held it, the share of its time (idling); the trip's end at the route's end, not at
    # the end of its last step (on the short track, which ends at speed, 0.44-0.61 s later:
    # 0.1-0.2 % of its fuel)
    end_moving = finished & ~arrived & ~standing
    share = jnp.where(end_moving, jnp.where(ds > 0, d_end / jnp.maximum(ds, 1e-12), 1.0),
                      jnp.where(finished & standing, st.dwell / dt, 1.0))
    v1 = jnp.where(end_moving, v_d, v1)
    s1 = jnp.where(end_moving, s0 + d_end, s1)
    h = dt * share  # the time the step counts
    P_bi = pt.battery_internal(vp, P_b)
    E_b1 = jnp.clip(st.E_b - P_bi * h - E_sync_b, 0.0, vp.E_b_max)

    live = ~st.done
    d = lambda x: jnp.where(live, x * h, z)  # noqa: E731
    tot = st.tot
    tot = Totals(
        fuel=tot.fuel + d(P_f + P_idle) + jnp.where(live, E_sync_f, 0.0),
        road=tot.road + jnp.where(live, F0 * ds * share, 0.0),
        loss_engine=tot.loss_engine + d(P_f - P_e + P_idle),
        loss_slip=tot.loss_slip + d(P_e - P_out),
        loss_motor=tot.loss_motor + d(P_b - P_m),
        loss_battery=tot.loss_battery + d(vp.beta * P_b * P_b),
        loss_brake=tot.loss_brake + d(-P_brake),
        loss_sync=tot.loss_sync + jnp.where(live, E_sync_b + E_sync_f, 0.0),
        mode_switches=tot.mode_switches + (mode_sw & live),
        gear_switches=tot.gear_switches + (gear_sw & live),
        max_shortfall=jnp.where(live & ~standing,
                                jnp.maximum(tot.max_shortfall, v_ref_here - v0), tot.max_shortfall),
        trip_time=jnp.where(live & finished, t_fin, tot.trip_time),
    )
    keep = lambda new, old: jnp.where(live, new, old)  # noqa: E731
    new = PlantState(
        s=keep(s1, st.s), v=keep(v1, st.v), E_b=keep(E_b1, st.E_b), mode=keep(mode, st.mode),
        gear=keep(gear, st.gear), open_left=keep(jnp.maximum(open_left - dt, 0.0), st.open_left),
        dwell=keep(dwell, st.dwell), served=keep(served, st.served),
        done=st.done | finished, tot=tot,
    )
    tr = Trace(t=k * dt, s=s0, v=v0, E_b=st.E_b, mode=mode, gear=gear, P_d=P_wheel * live,
               P_e=P_e * live, P_m=P_m * live, P_b=P_b * live, P_f=(P_f + P_idle) * live,
               P_brake=P_brake * live, lam=lam, v_ref=v_ref_here,
               E_sync_b=jnp.where(live, E_sync_b, z), E_sync_f=jnp.where(live, E_sync_f, z),
               counted=jnp.where(live, h, z))
    return (new, cparams, cstate), tr


def step_bounds(pred):
    """(T+1,) positions (m) of a Level 3 prediction's step starts and of the route's end (the
    masked steps after the trip at the end)."""
    return jnp.concatenate([jnp.where(pred.mask, pred.s, pred.length), pred.length[None]])


def make_track(route, pred, end_cap: bool = True) -> Track:
    """The plant's `Track` from a `Route` and its Level 3 `Prediction` (one route).

    end_cap (static): cap the battery's charge at its start energy from the reference's last
    step of positive power demand on (`Track.final_s`); False: no cap (+inf).
    """
    prof = pred.profile
    mask = pred.mask
    v_end = jnp.sum(jnp.where(last_node(prof.mask), prof.v, 0.0))
    ref_s = step_bounds(pred)
    ref_v = jnp.concatenate([jnp.where(mask, pred.v_ref, v_end), v_end[None]])
    is_stop = (jnp.asarray(route.stop) > 0) & jnp.asarray(route.mask)
    pos = jnp.where(is_stop, prof.s, jnp.inf)
    dur = jnp.where(is_stop, jnp.asarray(route.stop), 0.0)

    def back(c, x):  # first stop at or after each node, scanning from the end
        p, d = x
        c = jnp.where(jnp.isfinite(p), jnp.stack([p, d]), c)
        return c, c

    init = jnp.array([jnp.inf, 0.0], dtype=prof.s.dtype)
    _, nxt = jax.lax.scan(back, init, (pos, dur), reverse=True)
    stop_s = jnp.concatenate([nxt[:, 0], jnp.array([jnp.inf], prof.s.dtype)])
    stop_t = jnp.concatenate([nxt[:, 1], jnp.zeros(1, prof.s.dtype)])
    # the end of a route without a final stop: no stop; padding nodes lie beyond the end
    beyond = pred.length + 1.0 + jnp.arange(prof.s.shape[0])
    grid_s = jnp.where(jnp.asarray(route.mask), prof.s, beyond)
    # the end of the reference's last step that needs traction (the start when none does)
    pulls = mask & (pred.P_d > 0)
    last = jnp.max(jnp.where(pulls, jnp.arange(mask.shape[0]) + 1, 0))
    final_s = ref_s[last] if end_cap else jnp.asarray(jnp.inf, ref_s.dtype)
    return Track(ref_s=ref_s, ref_v=ref_v, grid_s=grid_s, grade=jnp.asarray(route.grade),
                 rise=node_rise(route, prof.s.dtype),
                 stop_s=stop_s, stop_t=stop_t, length=pred.length, final_s=final_s,
                 ref_c=None, grid_c=None).with_search_blocks()


def initial_state(vp: VehicleParams, track: Track, mode, gear, dtype=None) -> PlantState:
    """Start at the beginning of the route at the reference speed, E_b = soc0 * E_b_max."""
    f = jnp.zeros((), dtype or jnp.result_type(float))
    i = jnp.zeros((), jnp.int32)
    return PlantState(
        s=f + track.ref_s[0], v=f + track.ref_v[0], E_b=f + vp.soc0 * vp.E_b_max,
        mode=i + mode, gear=i + gear, open_left=f, dwell=f, served=f - 1.0,
        done=jnp.array(False),
        tot=Totals(*([f] * 8), i, i, f, f),
    )


def run_plant(vp: VehicleParams, track: Track, controller: Controller, cparams, cstate,
              init_mode, init_gear, n_steps: int, dt: float = 1.0) -> PlantResult:
    """Simulate the closed loop for `n_steps` steps of `dt` seconds (static), or until the end.

    Returns the final state (totals in `final.tot`) and per-step traces (n_steps,). If the route
    is not finished within n_steps, `final.done` is False (callers report it as a status).
    """
    st0 = initial_state(vp, track, init_mode, init_gear)
    step = lambda c, k: _step(vp, track, controller, dt, c, k)  # noqa: E731
    (final, _, _), trace = jax.lax.scan(step, (st0, cparams, cstate), jnp.arange(n_steps))
    return PlantResult(final=final, trace=trace, E_b0=st0.E_b)


def energy_balance(res: PlantResult, vp: VehicleParams):
    """(inputs, outputs) in J: fuel + battery drawn, and road work + kinetic change + losses."""
    t = res.final.tot
    e_in = t.fuel + (res.E_b0 - res.final.E_b)
    v0 = res.trace.v[0]
    dkin = 0.5 * vp.mass * (res.final.v**2 - v0**2)
    losses = (t.loss_engine + t.loss_slip + t.loss_motor + t.loss_battery + t.loss_brake
              + t.loss_sync)
    return e_in, t.road + dkin + losses
