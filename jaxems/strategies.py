"""Energy-management strategies, each run on the same plant and route (section 7).

- ``conventional``: the truck without its motor (engine-only and open modes), gears by the
  full-horizon Level 1 DP with switching costs. The non-hybrid reference of Tables 7 and 8. Its
  engine idles with the clutch open (a conventional truck has no start-stop).
- ``baseline``: a hybrid EMS without route preview, as a user would build one: an adaptive
  equivalent-consumption minimisation (A-ECMS). At every step it minimises the Hamiltonian of
  the *current* demand plus the switching cost from the current state (a one-step DP, no
  knowledge of the road ahead), with lambda_b from state-of-charge feedback,
  lambda_b = lambda0 + k_p ((E_b + k_e m v^2 / 2) / E_b_max - soc_ref), clipped to [-6, -0.3]:
  the feedback counts the share k_e of the kinetic energy that braking will return, so the
  battery keeps room for it while the truck is fast (a speed-dependent charge reference; it
  needs the measured speed only). By default soc_ref is what the trip starts with, counted
  the same way (the initial charge and the share of the start's kinetic energy), so that the
  feedback holds the charge the trip started with, whatever that is.
- ``multilevel``: the iteration scheme of section 3.3: Level 3 -> Level 2 -> Level 1 over the
  full horizon, `n_iter` times, omega (engine speed) and lambda_b fed back; iteration 0 starts
  from a constant engine speed (vehicle's ``prediction_engine_speed_rpm``, 1100 rpm as in
  Appendix D). Each iteration's decisions are run on the plant; the last one is the result.
- ``multilevel-mpc``: the MPC scheme of section 3.4 inside the plant loop: Level 2 on a window
  of `h2` samples re-solved every `t2` samples from the measured battery energy (I3 where the
  window ends before the route, charge sustaining within the battery's limits where it reaches
  the end; omega at 1100 rpm except on steady descents, `mpc_omega`), Level 1 as a DP
  over `h1` samples from the measured mode and gear, applying the first decision. Level 3 is
  indexed by position: re-planning it from the measured position over a 1000 s window gives the
  same reference as the full-route profile restricted to the window (the forward/backward
  passes are position-indexed), so it is computed once per route.
- ``multilevel-eco``: ``multilevel`` on an eco-driving speed profile: Level 3 optimises the
  speed (`velocity.optimize_velocity`: fuel-equivalent energy at Level 2's charge-sustaining
  lambda_b plus lambda_t times the trip time, under Level 3's own profile), with lambda_t found
  by bisection so that the trip time is Level 3's (times ``eco_time_ratio``; within 0.5 %), or
  given (``eco_lambda_t``). Where the route allows the cruise speed v0, the speed may exceed it
  by ``eco_overspeed_kmh`` (5 km/h: 85 -> 90 km/h, a predictive cruise control's band), so that
  time given up before a crest is regained on the descent. The speed stays fixed over the
  iterations (omega and lambda_b are fed back as in ``multilevel``).
- ``dp-bound``: the global optimum of problem (21) with the velocity fixed to the Level 3
  prediction: a backward dynamic program over (E_b grid x mode x gear) with the same switching
  costs, charge sustaining through a terminal penalty, then a forward rollout from the exact
  E_b(t0) (interpolating the value function) whose decisions run on the same plant.

Kernels are pure functions of one route and one vehicle (jit/vmap at the edge); `simulate`
is the host API and `simulate_batch` the batched one used by sweeps. The Level 1 that keeps
Level 2's battery plan, and the plan the plant follows, are in `jaxems.plan`; dp-bound's DP
is in `jaxems.bound`.
"""

from __future__ import annotations

import functools
import math
import numbers
import os
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from . import dp, shard
from . import plant as pl
from . import powertrain as pt
from . import switching as sw
from .levels import battery as l2
from .levels import level1 as l1
from .levels import powersplit as ps
from .levels import velocity as l3
from .bound import bound_dp, bound_pieces, bound_tables
from .params import (
    VehicleError,
    VehicleParams,
    check_vehicle,
    load_vehicle,
    stack_vehicles,
    with_overrides,
)
from .plan import (
    Drift,
    Plan,
    compensate,
    guard_lambda,
    level1,
    make_plan,
    no_drift,
    piece_targets,
    plan_controller,
    plant_drift,
    sustaining_level1,
)
from .route import Route, RouteError, check_route
from .xla import jit

STRATEGIES = ("conventional", "baseline", "multilevel", "multilevel-mpc", "dp-bound",
              "multilevel-eco")
PAPER_STRATEGIES = STRATEGIES[:5]  # the rows of the paper's Table 8
HYBRID = ("baseline", "multilevel", "multilevel-mpc", "dp-bound", "multilevel-eco")

MAX_STEPS = 2**23  # the most Level 3 steps `simulate_batch` takes (97 days at 1 s)

# status codes of a run (bit flags) and their names
OK, INFEASIBLE_ROUTE, UNFINISHED, ECO_TIME, STEPS_SHORT = 0, 1, 2, 4, 8
STATUS_NAMES = {INFEASIBLE_ROUTE: "infeasible-route", UNFINISHED: "unfinished",
                ECO_TIME: "eco-trip-time-missed", STEPS_SHORT: "level3-steps-short"}


class Options(NamedTuple):
    """Options of the strategies (hashable). A change of one recompiles, but for the numbers
    in `TRACED_OPTIONS`, which `simulate` and `simulate_batch` pass to the compiled program
    as arguments.

    n_iter: multilevel iterations (>= 1); h1: Level 1 MPC horizon (samples); h2: Level 2 MPC
    window (samples); t2: Level 2 MPC sample time (samples); lam0, kp, soc_ref, ke_share,
    dwell, ecms_horizon: baseline A-ECMS (ke_share: share of the kinetic energy its charge
    feedback counts as in the battery already; soc_ref: the charge it holds, as a fraction of
    E_b_max with that share counted, None: the trip's start, `ecms_params`; dwell: least time
    (s) between its switches; ecms_horizon: the time (s) over which its one-step choice weighs
    a state's Hamiltonian against the cost of switching into it, `ecms_controller`; 3 s, as
    the dwell that a switch commits the truck to);
    dp_n_E: E_b grid points of dp-bound; dp_lams: number of costate values whose Level 1 splits
    are dp-bound's battery-power candidates; dp_penalty: fuel J per J of E_b(tf) away from
    E_b(t0) in dp-bound's terminal cost, beyond Level 2's costate (`bound_dp`); dp_attempts:
    dp-bound's DP and plant runs, each from the last one's plant drift and engine speeds;
    plant_extra: plant steps beyond Level 3's (slack for switching delays, as a fraction; at
    least 256 steps); sustain: make each multilevel Level 1 plan charge sustaining on its own
    model (`sustaining_level1`); guard_sides: Level 1 follows Level 2's I2b sides at guards
    (`guard_lambda`); l2_pieces: the most pieces of Level 2's piecewise-constant costate (I1);
    tau_E: time constant (s) of the plant's battery-power feedback on the deviation from a
    plan's battery energy; same_open_time: every vehicle has dt_M == dt_G, so Level 1 takes the
    fast relaxation without a runtime branch (set by `simulate` and `simulate_batch` from the
    vehicles; None: decided at run time); eco_lambda_t: multilevel-eco's price of a second (J/s;
    None: found so that the trip takes eco_time_ratio times Level 3's trip time, a ratio in [1,
    1.5]); eco_overspeed_kmh: how far above the cruise speed v0 eco-driving may go where the
    route allows v0 (km/h, 0 to 15; `velocity.speed_bounds`; 0: never faster than Level 3, which
    then leaves no freedom at Level 3's trip time); mpc_pieces: the most pieces of the MPC's
    Level 2 where its window reaches the route's end (I1 within the battery's limits; 1: plain
    bisection, cheaper in a batch, where vmap evaluates both branches of the controller's every
    step); end_cap: from the reference's last step of positive power demand to the route's end
    (its final braking), the plant's battery stores no more than the trip started with and the
    service brakes take the rest (`plant.Track.final_s`; False: it stores all it can);
    mpc_end_reserve: share of the battery the MPC aims its end above the start where that cap
    applies (`mpc_end_target`); end_reserve: the same for the last plan of the multilevel
    iteration, on its trip's last Level 2 piece (`end_reserve`, `level1_targets`);
    level0_plan_power: below a plan's battery energy, Level 0 counts
    only the plan's battery power in the engine's states when it asks whether a state serves
    (`plant.Command.level0_plan`: where the plan's gear cannot hold the speed on its engine,
    the driveline shifts down; False: it counts what the battery holds, as before 2026-11-27,
    and holds the speed on the battery); trim_excursions: a plan's battery-power trim splits
    each of its pieces where the plan's own path leaves the battery's limits furthest
    (`excursion_pieces`; multilevel's and dp-bound's plans; False: the pieces as they are, as
    before 2026-11-28). The whole-number options have upper bounds too (`make_options`): they
    size arrays and loops, and a typo must not run a machine out of memory.
    """

    n_iter: int = 2
    h1: int = 5
    h2: int = 1000
    t2: int = 1
    lam0: float = -2.2
    kp: float = 5.0
    soc_ref: float | None = None
    ke_share: float = 0.05
    dwell: float = 3.0
    ecms_horizon: float = 3.0
    dp_n_E: int = 101
    dp_lams: int = 48
    dp_penalty: float = 1.0
    dp_attempts: int = 3
    plant_extra: float = 0.15
    sustain: bool = True
    guard_sides: bool = True
    l2_pieces: int = 32
    tau_E: float = 60.0
    same_open_time: bool | None = None
    eco_lambda_t: float | None = None
    eco_time_ratio: float = 1.0
    eco_overspeed_kmh: float = 5.0
    mpc_pieces: int = 8
    end_cap: bool = True
    mpc_end_reserve: float = 0.03
    end_reserve: float = 0.01
    level0_plan_power: bool = True
    trim_excursions: bool = True


class Metrics(NamedTuple):
    """What a run reports; scalars (one route, one vehicle). level3_trip_time_s: Level 3's
    trip time on the prediction the run followed (the iteration's and dp-bound's last,
    re-predicted with their engine speeds; the eco profile's), against which the trip-time
    check reads trip_time_s (`report.trip_long`). level2_status: the flags of the last plan's
    Level 2 (`levels.battery.STATUS_NAMES`; 0 converged, PIECES_EXHAUSTED: its `l2_pieces`
    ran out with the battery's limits still violated) for the strategies that iterate
    (multilevel, multilevel-eco); NO_LEVEL2 for the others. A run that did not reach the
    route's end (status UNFINISHED) has no trip time: NaN (null in JSON), and its fuel and
    battery figures are over the steps it ran."""

    length_m: Any
    trip_time_s: Any
    level3_trip_time_s: Any  # Level 3's trip time on the prediction the run followed last
    fuel_J: Any
    delta_Eb_J: Any
    Eb_min_J: Any
    Eb_max_J: Any
    mode_switches: Any
    gear_switches: Any
    lambda_b: Any
    max_speed_shortfall_mps: Any
    status: Any
    level2_status: Any


NO_LEVEL2 = -1  # Metrics.level2_status of a strategy without the iteration's Level 2


def level2_names(code) -> list[str] | None:
    """A `Metrics.level2_status` by name: None for NO_LEVEL2, [] converged, else the flags
    (`levels.battery.status_names`)."""
    code = int(code)
    return None if code == NO_LEVEL2 else l2.status_names(code)


class Run(NamedTuple):
    """A kernel's output: metrics, the plant run, the Level 3 prediction, and extras."""

    metrics: Metrics
    plant: pl.PlantResult
    pred: l3.Prediction
    extra: Any


# ------------------------------------------------------------------------------ building blocks
def level3(route: Route, vp: VehicleParams, dt, n_steps: int, w_nodes=None) -> l3.Prediction:
    """Level 3 inside a kernel: profile on the distance grid, resampled to n_steps (static)."""
    N = route.grade.shape[-1]
    w = jnp.broadcast_to(vp.w_pred if w_nodes is None else w_nodes, (N,))
    prof = l3.velocity_profile(route, vp, w)
    return l3.resample(route, vp, prof, dt, n_steps)


def plant_steps(n_steps: int, opts: Options) -> int:
    extra = max(256, int(math.ceil(n_steps * opts.plant_extra)))
    return int(math.ceil((n_steps + extra) / 64) * 64)


def _first_state(vp, pred, lam):
    """Open driveline at a standing start; else the Hamiltonian's best state at step 0."""
    _, m, g = ps.optimal_mode_gear(ps.mode_gear_split(vp, pred.P_d[0], pred.v[0], lam))
    standing = pred.v_ref[0] <= 0
    return jnp.where(standing, ps.MO, m), jnp.where(standing, 0, g)


def _run_plan(vp, track: pl.Track, pred, plan: Plan, n_plant, dt):
    """Run a plan on the plant (`track`: `plant.make_track` of the plan's prediction), starting
    in its first state (open driveline when standing)."""
    standing = pred.v_ref[0] <= 0
    m0 = jnp.where(standing, ps.MO, plan.mode[0])
    g0 = jnp.where(standing, 0, plan.gear[0])
    return pl.run_plant(vp, track, plan_controller, plan, jnp.zeros(()), m0, g0, n_plant, dt)


def _metrics(res: pl.PlantResult, pred: l3.Prediction, vp, lam_b, status,
             level2=NO_LEVEL2) -> Metrics:
    t = res.final.tot
    E = res.trace.E_b
    status = status | jnp.where(pred.feasible, OK, INFEASIBLE_ROUTE)
    status = status | jnp.where(res.final.done, OK, UNFINISHED)
    # Level 3's trip does not fit its steps (`simulate_batch`'s n_steps too few): the
    # prediction, and the run that followed it, were cut short
    status = status | jnp.where(pred.trip_time < pred.v.shape[0] * pred.dt, OK, STEPS_SHORT)
    return Metrics(
        length_m=pred.length, trip_time_s=jnp.where(res.final.done, t.trip_time, jnp.nan),
        level3_trip_time_s=jnp.asarray(pred.trip_time, E.dtype), fuel_J=t.fuel,
        delta_Eb_J=res.final.E_b - res.E_b0,
        Eb_min_J=jnp.minimum(jnp.min(E), res.final.E_b),
        Eb_max_J=jnp.maximum(jnp.max(E), res.final.E_b),
        mode_switches=t.mode_switches, gear_switches=t.gear_switches,
        lambda_b=jnp.asarray(lam_b, E.dtype), max_speed_shortfall_mps=t.max_shortfall,
        status=jnp.asarray(status, jnp.int32),
        level2_status=jnp.asarray(level2, jnp.int32),
    )


def _engine_speed_nodes(route, pred, w_steps):
    """Map a per-step engine speed (T,) to the route's nodes (N,) by position (Level 3 input)."""
    prof = pred.profile
    moving = pred.mask & (pred.v > 0)
    s = jnp.where(moving, pred.s, jnp.inf)
    order = jnp.argsort(s)
    s_sorted = s[order]
    w_sorted = w_steps[order]
    n_valid = jnp.sum(moving)
    last = jnp.maximum(n_valid - 1, 0)
    s_sorted = jnp.where(jnp.arange(s.shape[0]) < n_valid, s_sorted, s_sorted[last] + 1.0
                         + jnp.arange(s.shape[0]))
    w_sorted = jnp.where(jnp.arange(s.shape[0]) < n_valid, w_sorted, w_sorted[last])
    return jnp.interp(prof.s, s_sorted, w_sorted)


def repredict_level3(route, vp, dt, n_steps: int, pred: l3.Prediction, mode, w) -> l3.Prediction:
    """Level 3 again, with the engine at the plan's speed w (T,) where the plan runs it (mode
    (T,) M_c or M_e, moving) and at the prediction's default speed elsewhere: its traction
    limit assumes the engine at that speed (the iteration's omega fed back to Level 3).

    Where that prediction stalls and pred did not, pred is returned: a node's speed holds for
    its whole cell in Level 3, and a launch's slipping clutch (the plan's engine at idle speed,
    its gear's speed rising through the cell) or a crawl behind a stall fed back as the engine's
    speed up a steep climb makes Level 3 stall where the truck climbs (a stop at the foot of a
    30 % climb: the plant climbs it in gear 1 on either prediction)."""
    w_e = jnp.where(engine_runs(pred, mode), jnp.clip(w, vp.we_min, vp.we_max), vp.w_pred)
    new = level3(route, vp, dt, n_steps, _engine_speed_nodes(route, pred, w_e))
    keep = new.feasible | ~pred.feasible
    return jax.tree_util.tree_map(lambda a, b: jnp.where(keep, a, b), new, pred)


def engine_runs(pred: l3.Prediction, mode):
    """(T,) bool: the plan (mode (T,)) runs the engine there, moving."""
    return pred.mask & (pred.v > 0) & ((mode == ps.MC) | (mode == ps.ME))


# ------------------------------------------------------------------------------ strategies
def _lam_conventional(vp):
    """Fuel value of mechanical energy at the crank: prices synchronisation without a battery."""
    return -1.0 / vp.eta_e


def run_conventional(route, vp, dt, n_steps: int, opts: Options, params) -> Run:
    vpc = vp.conventional()
    pred = level3(route, vpc, dt, n_steps)
    lam = _lam_conventional(vpc)
    r1 = level1(vpc, pred, lam, dt, params, opts.same_open_time)
    plan = make_plan(vpc, r1.mode, r1.gear, r1.P_b, lam, pred, dt, opts)
    track = pl.make_track(route, pred, opts.end_cap)
    res = _run_plan(vpc, track, pred, plan, plant_steps(n_steps, opts), dt)
    return Run(_metrics(res, pred, vpc, 0.0, OK), res, pred, r1)


class EcmsParams(NamedTuple):
    lam0: Any
    kp: Any
    soc_ref: Any
    ke_share: Any
    dwell: Any  # s
    switch: sw.SwitchCostParams
    dt: Any  # the plant's time step (s)
    horizon: Any  # s over which a state's Hamiltonian (W) is weighed against a switch (J)


def ecms_lambda(p: EcmsParams, vp, E_b, v):
    """A-ECMS costate from charge feedback (no preview): E_b (J) and the speed v (m/s) now."""
    soc = (E_b + p.ke_share * 0.5 * vp.mass * v**2) / vp.E_b_max
    return jnp.clip(p.lam0 + p.kp * (soc - p.soc_ref), l2.LAM_BRACKET[0], l2.LAM_BRACKET[1])


def ecms_controller(p: EcmsParams, cstate, vp, obs: pl.Obs):
    """One-step DP: each state's Hamiltonian over the payback horizon (H horizon, J) plus the
    switching cost (J) from the current state, with a minimum dwell time (s) between switches
    (as shift logic has), unless the current state cannot serve (the plant's protection then
    switches anyway). A switch commits the truck to its new state for at least the dwell, so
    its gain is weighed over that long by default (`Options.ecms_horizon`): weighed over one
    second, a downshift that lets the motor recuperate a descent never paid for itself (on the
    short track's descents the service brakes took 150-170 kW beside 20 kW of recuperation,
    and from an empty battery the truck never recuperated). Both are times, not steps, so the
    decisions do not change with the plant's step dt beyond its resolution (`since`: the
    steps since the last switch)."""
    since = cstate  # steps since the last switch
    lam = ecms_lambda(p, vp, obs.E_b, obs.v)
    tab = ps.mode_gear_split(vp, obs.P_req, obs.v_op, lam)
    n_g = vp.gear_ratio.shape[-1]
    s_cur = obs.mode * n_g + obs.gear
    # (not `level1.braking_loss`: this DP weighs a switch over its horizon only, not over the
    # braking it serves; with one step weighed it would never have switched into braking)
    C = sw.switch_cost_matrix(vp, obs.v_op, obs.grade, lam, p.switch)[s_cur]
    cost = jnp.where(tab.feasible, tab.H * p.horizon, jnp.inf).reshape(-1) + C
    i = jnp.argmin(cost)
    dwelt = since * p.dt >= p.dwell * (1 - 1e-6)  # (rounding: 3 steps of 1/3 s are 1 s)
    i = jnp.where(jnp.isfinite(cost[i]) & dwelt, i, s_cur)
    since = jnp.where(i == s_cur, since + 1, 0).astype(since.dtype)
    return since, pl.Command(mode=i // n_g, gear=i % n_g, lam=lam, P_b=jnp.nan)


def ecms_params(vp, track: pl.Track, opts: Options, params, dt) -> EcmsParams:
    """The A-ECMS baseline's `EcmsParams`. Its charge reference soc_ref, unless opts gives one,
    is what the trip starts with as its feedback counts it: (E_b(t0) + ke_share m v(t0)^2 / 2)
    / E_b_max, from the plant's initial state (no preview): the charge the trip started with
    is what it holds, at the start's speed (a fixed 0.5 drove a trip that started at 30 or 70 %
    of the battery to half, 6-15 % of the battery off on Regional Delivery)."""
    if opts.soc_ref is None:
        v0 = track.ref_v[0]
        soc_ref = (vp.soc0 * vp.E_b_max + opts.ke_share * 0.5 * vp.mass * v0**2) / vp.E_b_max
    else:
        soc_ref = jnp.asarray(opts.soc_ref)
    dtype = jnp.asarray(vp.E_b_max).dtype
    return EcmsParams(lam0=jnp.asarray(opts.lam0), kp=jnp.asarray(opts.kp), soc_ref=soc_ref,
                      ke_share=jnp.asarray(opts.ke_share), dwell=jnp.asarray(opts.dwell),
                      switch=params, dt=jnp.asarray(dt, dtype),
                      horizon=jnp.asarray(opts.ecms_horizon, dtype))


def run_baseline(route, vp, dt, n_steps: int, opts: Options, params) -> Run:
    pred = level3(route, vp, dt, n_steps)
    track = pl.make_track(route, pred, opts.end_cap)
    p = ecms_params(vp, track, opts, params, dt)
    res = pl.run_plant(vp, track, ecms_controller, p, jnp.asarray(0, jnp.int32), ps.MO, 0,
                       plant_steps(n_steps, opts), dt)
    lam_first = res.trace.lam[0]
    return Run(_metrics(res, pred, vp, lam_first, OK), res, pred, None)


class Iteration(NamedTuple):
    """Per iteration of the multilevel scheme: fuel (J), delta E_b (J), lambda_b(t0), Level
    2's status and the plan the plant ran (`Plan`; `experiments/plan_tracking.py` reads it)."""

    fuel_J: Any
    delta_Eb_J: Any
    lambda_b: Any
    costate_status: Any
    plan: Any


def run_multilevel(route, vp, dt, n_steps: int, opts: Options, params) -> Run:
    return _iterate(route, vp, dt, n_steps, opts, params, level3(route, vp, dt, n_steps), True)


def level1_targets(vp, pred, c2: l2.CostateResult, drift: Drift, opts: Options, reserve=0.0):
    """What an iteration's Level 1 gets of Level 2: the costate (T,) (moved to the side of
    Level 2's I2b sequence at guards, `guard_lambda`, if opts.guard_sides) and Level 2's pieces
    (pid (T,), target (K,)), made up for the battery drift the plant showed on the last
    iteration (`compensate`), the route's last piece raised by `reserve` (J, `end_reserve`)."""
    lam_g = guard_lambda(c2, 1e-3 * vp.E_b_max) if opts.guard_sides else c2.lam
    pid, target = compensate(piece_targets(c2, pred.v.shape[0]), pred, c2.boundaries, drift)
    last = pid[jnp.maximum(jnp.sum(pred.mask) - 1, 0)]  # the piece of the trip's last step
    return lam_g, (pid, target.at[last].add(reserve))


def _unless_last(i, n: int, feedback, carry):
    """What step i (a scan's index, not batched) of n passes on to the next: feedback(), or on
    the last step, which has no next, the carry unchanged (under vmap the cond stays one, and
    the last step skips the work)."""
    return jax.lax.cond(i < n - 1, feedback, lambda: carry)


def _iterate(route, vp, dt, n_steps: int, opts: Options, params, pred0, repredict: bool) -> Run:
    """The iteration scheme from the prediction pred0; repredict (static): Level 3 re-predicts
    with Level 1's engine speed each iteration (else the speed profile stays pred0's)."""
    n_plant = plant_steps(n_steps, opts)
    # a batch (a sweep's chunk) runs Level 2 and the plan-keeping Level 1 one configuration at
    # a time on a CPU, where their conds and loops cost more vectorised, and the plant
    # vectorised
    _sustaining = shard.one_at_a_time(
        lambda vp, pred, lam, params, pid, target: sustaining_level1(
            vp, pred, lam, dt, params, pid, target, fast=opts.same_open_time))
    _level2 = shard.one_at_a_time(
        lambda vp, P_d, v, w, mask: l2.costate_kernel(vp, P_d, v, w, mask, dt,
                                                      max_pieces=opts.l2_pieces))

    def iteration(carry, i):
        pred, w, drift = carry
        track = pl.make_track(route, pred, opts.end_cap)
        c2 = _level2(vp, pred.P_d, pred.v, w, pred.mask)
        # the last iteration's plan, whose plant run is the result, keeps a reserve at the end
        # (the earlier ones measure the plant's drift from the plan without it)
        reserve = jnp.where(i == opts.n_iter - 1, end_reserve(vp, track, opts.end_reserve), 0.0)
        lam_g, pieces = level1_targets(vp, pred, c2, drift, opts, reserve)
        if opts.sustain:
            r1, lam1 = _sustaining(vp, pred, lam_g, params, *pieces)
        else:
            r1, lam1 = level1(vp, pred, lam_g, dt, params, opts.same_open_time), lam_g
        plan = make_plan(vp, r1.mode, r1.gear, r1.P_b, lam1, pred, dt, opts, pieces)
        res = _run_plan(vp, track, pred, plan, n_plant, dt)
        it = Iteration(res.final.tot.fuel, res.final.E_b - res.E_b0, c2.lam0, c2.status, plan)
        # feed back the speed omega of Level 1's gears where the engine runs, to Level 2 (its
        # gear) and Level 3 (its traction limit assumes the engine at that speed); where Level 1
        # drives on the motor or coasts, the estimate stays (a gear in which the engine cannot
        # run would forbid Level 2 the engine there)
        def feedback():
            w_new = jnp.where(engine_runs(pred, r1.mode), r1.w, w)
            if repredict:
                pred_new = repredict_level3(route, vp, dt, n_steps, pred, r1.mode, r1.w)
            else:
                pred_new = pred
            return pred_new, w_new, plant_drift(pred, plan, res)

        return _unless_last(i, opts.n_iter, feedback, carry), (it, res, pred)

    w0 = jnp.full_like(pred0.v, vp.w_pred)
    _, (its, ress, preds) = jax.lax.scan(iteration, (pred0, w0, no_drift(pred0)),
                                         jnp.arange(opts.n_iter))
    last = lambda tree: jax.tree_util.tree_map(lambda x: x[-1], tree)  # noqa: E731
    res, pred = last(ress), last(preds)
    # Level 2's own flags (at a guard, pieces exhausted, ...) are not the run's status: the run
    # is complete whatever they say, and its battery balance is reported; the last plan's are
    # reported apart (level2_status), every iteration's in `extra`
    return Run(_metrics(res, pred, vp, its.lambda_b[-1], OK, its.costate_status[-1]), res, pred,
               its)


class EcoExtra(NamedTuple):
    """multilevel-eco's extras: the iterations, lambda_t (J/s) and lambda_b of the speed
    optimisation, the trip time of Level 3's own prediction (s) and the optimiser's status
    (`velocity.eco_status_names`)."""

    iterations: Iteration
    lambda_t: Any
    lambda_b: Any
    level3_trip_time: Any
    eco_status: Any


def eco_costate(vp, pred: l3.Prediction, dt):
    """The lambda_b that prices battery energy in the eco-driving objective: Level 2's
    charge-sustaining costate on Level 3's prediction (one piece, without battery limits)."""
    w = jnp.full_like(pred.v, vp.w_pred)
    return l2.costate_kernel(vp, pred.P_d, pred.v, w, pred.mask, dt, E_min=-jnp.inf,
                             E_max=jnp.inf, max_pieces=1).lam0


def eco_speed(route, vp, dt, n_steps: int, opts: Options):
    """Level 3 with eco-driving for one route and one vehicle: (`velocity.EcoResult`,
    lambda_b, Level 3's own `Prediction`)."""
    pred3 = level3(route, vp, dt, n_steps)
    lam_b = eco_costate(vp, pred3, dt)
    band = opts.eco_overspeed_kmh / 3.6
    if opts.eco_lambda_t is None:
        _, eco = l3.match_trip_time(route, vp, pred3.trip_time * opts.eco_time_ratio, lam_b,
                                    overspeed=band)
    else:
        eco = l3.optimize_velocity(route, vp, opts.eco_lambda_t, lam_b, overspeed=band)
    return eco, lam_b, pred3


def run_multilevel_eco(route, vp, dt, n_steps: int, opts: Options, params) -> Run:
    eco, lam_b, pred3 = eco_speed(route, vp, dt, n_steps, opts)
    pred0 = l3.resample(route, vp, eco.profile, dt, n_steps)
    run = _iterate(route, vp, dt, n_steps, opts, params, pred0, False)
    missed = (eco.status & (l3.ECO_TARGET_FAST | l3.ECO_TARGET_SLOW | l3.ECO_TARGET_MISSED)) > 0
    # a profile longer than the step grid would be cut: flag it (steps_for_batch sizes the grid)
    missed = missed | (eco.trip_time > n_steps * dt)
    m = run.metrics._replace(status=run.metrics.status | jnp.where(missed, ECO_TIME, OK))
    extra = EcoExtra(run.extra, eco.lambda_t, lam_b, pred3.trip_time, eco.status)
    return Run(m, run.plant, run.pred, extra)


class MpcParams(NamedTuple):
    P_d: Any  # (T + h,) the Level 3 prediction, padded for the windows
    v: Any
    grade: Any
    mask: Any
    w: Any  # (T + h,) engine speed assumed by Level 2 (constant, as iteration 0)
    gears: Any  # Level 2's steps at their gears at w (`battery.step_model`: gear, ok and the
    # lambda-free step table, (T + h,) each), sliced for each window (both are step by step)
    end: Any  # () index of the last valid step
    E_target: Any  # () E_b at the end of the route (charge sustaining)
    dt: Any
    switch: sw.SwitchCostParams


def _mpc_controller(h1: int, h2: int, t2: int, pieces: int, l2_iter: int = 24):
    def ctrl(p: MpcParams, cstate, vp, obs: pl.Obs):
        lam_prev, k_last = cstate
        j = obs.j
        win2 = lambda a: jax.lax.dynamic_slice_in_dim(a, j, h2)  # noqa: E731
        covers_end = j + h2 > p.end
        args = (win2(p.P_d), win2(p.v), win2(p.w), win2(p.mask), p.dt)
        gears = jax.tree.map(win2, p.gears)

        def to_end():  # the window reaches the route's end: charge sustaining there, within
            # the battery's limits (I1, up to `pieces` pieces: the first piece's costate is
            # applied); at a guard, the side of Level 2's I2b sequence now (as `guard_lambda`)
            c2 = l2.costate_kernel(vp, *args, E_b0=obs.E_b, E_b_end=p.E_target,
                                   n_iter=l2_iter, max_pieces=pieces, gears=gears)
            return guard_lambda(c2, 1e-3 * vp.E_b_max)[0]

        def limited():  # I3: the largest distance to the battery limits over the window
            return l2.horizon_kernel(vp, *args, obs.E_b, n_iter=l2_iter, max_pieces=1,
                                     gears=gears).lam

        due = (obs.k - k_last) >= t2
        lam_new = jax.lax.cond(due, lambda: jax.lax.cond(covers_end, to_end, limited),
                               lambda: lam_prev.astype(p.P_d.dtype))
        lam = jnp.where(due, lam_new, lam_prev).astype(lam_prev.dtype)
        k_last = jnp.where(due, obs.k, k_last).astype(k_last.dtype)
        return (lam, k_last), mpc_level1(p, vp, obs, lam, h1)

    return ctrl


def mpc_level1(p: MpcParams, vp, obs: pl.Obs, lam, h1: int) -> pl.Command:
    """The MPC's Level 1: a DP over the next h1 samples from the measured mode and gear at
    costate lam (), its first decision applied; the plant splits the power at lam."""
    win1 = lambda a: jax.lax.dynamic_slice_in_dim(a, obs.j + 1, h1)  # noqa: E731
    tb = l1.dp_inputs(vp, win1(p.P_d), win1(p.v), win1(p.grade), lam, p.dt, p.switch)
    S = tb.stage.shape[1]
    n_g = S // ps.N_MODES
    s_cur = obs.mode * n_g + obs.gear
    init = jnp.where(jnp.arange(S) == s_cur, 0.0, jnp.inf).astype(tb.stage.dtype)
    s0, cost = dp.viterbi_first(tb.stage, l1.structured_transition(tb.xs, tb.consts), init,
                                win1(p.mask))
    s0 = jnp.where(jnp.isfinite(cost), s0, s_cur)
    return pl.Command(mode=s0 // n_g, gear=s0 % n_g, lam=lam, P_b=jnp.nan)


STEADY_ACCEL = 0.05  # m/s^2: below this the reference holds its speed (a descent's braking)


def mpc_omega(vp, pred: l3.Prediction):
    """Level 2's engine-speed estimate omega for the MPC: (T,) rad/s.

    The MPC does not iterate, so no Level 1 gear is fed back. Its estimate is the constant
    1100 rpm of iteration 0, except where the reference brakes at a steady speed (a descent):
    there Level 1 holds the gear that recuperates most, and omega is that gear's shaft speed
    (steady: the step's mean acceleration `pred.a` below STEADY_ACCEL).
    At 1100 rpm Level 2 takes a high gear that limits the motor's recuperation (short track,
    last descent: 63 against 88 kW), so it under-predicts what the descent returns. In
    decelerations Level 1 shifts down through the gears, so 1100 rpm stays there.
    """
    sp = jax.vmap(ps.mode_gear_split, in_axes=(None, 0, 0, None))(vp, pred.P_d, pred.v, -2.0)
    Pb = jnp.min(jnp.where(sp.feasible, sp.P_b, jnp.inf), axis=1)  # (T, G) over the modes
    g = jnp.argmin(Pb, axis=-1)
    w_g = jnp.take_along_axis(pt.shaft_speeds(vp, pred.v), g[:, None], axis=-1)[:, 0]
    descent = ((pred.P_d < 0) & (jnp.abs(pred.a) < STEADY_ACCEL)
               & jnp.isfinite(jnp.min(Pb, axis=-1)))
    return jnp.where(descent, w_g, vp.w_pred)


def end_reserve(vp, track: pl.Track, share):
    """The battery energy (J) a plan aims its end above the start's: `share` of the battery
    where the route ends in a final braking that the plant caps at the start's energy
    (`end_cap`), else 0. Storing beyond the start there is thrown away, so the reserve costs
    little fuel, and it covers what the plant moves of the battery unlike the plan."""
    capped = track.final_s < track.length  # a stretch without traction before the end
    return jnp.where(capped, share * vp.E_b_max, 0.0)


def mpc_end_target(vp, track: pl.Track, opts: Options):
    """E_b (J) the MPC's Level 2 aims at for the route's end: the start's energy, raised by
    `end_reserve` of `mpc_end_reserve` (on Long Haul the plant, behind the reference after
    upshifts, catches up on the battery before the final braking: 2.7 % of the battery low
    without it)."""
    E0 = vp.soc0 * vp.E_b_max
    return jnp.minimum(E0 + end_reserve(vp, track, opts.mpc_end_reserve), vp.E_b_max)


def mpc_params(vp, pred: l3.Prediction, track: pl.Track, dt, opts: Options,
               params) -> MpcParams:
    """The MPC controller's `MpcParams` on a Level 3 prediction and its track."""
    h = max(opts.h1 + 1, opts.h2)
    padf = lambda a: jnp.concatenate([a, jnp.zeros(h, a.dtype)])  # noqa: E731
    end = jnp.maximum(jnp.sum(pred.mask) - 1, 0)
    P_d, v, w = padf(pred.P_d), padf(pred.v), padf(mpc_omega(vp, pred))
    mask = jnp.concatenate([pred.mask, jnp.zeros(h, bool)])
    return MpcParams(P_d=P_d, v=v, grade=padf(pred.grade), mask=mask, w=w,
                     gears=l2.step_model(vp, P_d, v, w, mask), end=end,
                     E_target=mpc_end_target(vp, track, opts),
                     dt=jnp.asarray(dt, pred.v.dtype), switch=params)


def run_multilevel_mpc(route, vp, dt, n_steps: int, opts: Options, params, ctrl=None) -> Run:
    """The MPC in the plant loop; ctrl: another controller on its `MpcParams` and its state
    (lam_b, the step of the last Level 2 solve), e.g. `mpc_level1` at a given costate
    (experiments/mpc_gap.py); None: the MPC's own."""
    pred = level3(route, vp, dt, n_steps)
    track = pl.make_track(route, pred, opts.end_cap)
    p = mpc_params(vp, pred, track, dt, opts, params)
    if ctrl is None:
        ctrl = _mpc_controller(opts.h1, opts.h2, opts.t2, pieces=opts.mpc_pieces)
    c0 = (jnp.asarray(opts.lam0, pred.v.dtype), jnp.asarray(-10**6, jnp.int32))
    m0, g0 = _first_state(vp, pred, opts.lam0)
    res = pl.run_plant(vp, track, ctrl, p, c0, m0, g0, plant_steps(n_steps, opts), dt)
    lam_first = res.trace.lam[0]
    return Run(_metrics(res, pred, vp, lam_first, OK), res, pred, None)


# ------------------------------------------------------------------------------ DP bound


class BoundExtra(NamedTuple):
    """dp-bound's own figures: the DP's predicted fuel (J), its E_b(tf) (J, counting the plant
    drift it was given), the target it had, and the plan the plant ran (its rollout: mode,
    gear, the costate whose Level 1 split was chosen at each step, the trimmed battery
    power)."""

    fuel_dp_J: Any
    E_end_dp_J: Any
    E_goal_J: Any  # the DP's target E_b(tf): E_b(t0), moved by what the last attempt missed
    plan: Any  # `Plan`


def run_dp_bound(route, vp, dt, n_steps: int, opts: Options, params) -> Run:
    pred0 = level3(route, vp, dt, n_steps)
    dtype = pred0.v.dtype
    E0 = vp.soc0 * vp.E_b_max
    n_g = vp.gear_ratio.shape[-1]

    def attempt(carry, k):
        """One DP, its plan and plant run. The DP's battery counts the drift the last plant
        run showed against its plan (by position), so that its own path follows the plant's;
        from the third attempt on, its goal also moves by the last attempt's miss (integral
        action on top of that drift, which the drift already contains once: an empirical
        choice, on Urban Delivery the third attempt ends 0.42 % of the battery low with it,
        2.6 % without).
        Its decisions become a plan (battery power trimmed so that the plan's own model,
        which counts the synchronisation energy the DP does not see, meets the DP's path
        without the drift where it reaches or leaves the battery's limits, and ends where that
        drift is made up: `bound_pieces`) that runs on the plant; the next attempt's Level 3
        prediction has the engine at this DP's speeds (as the iteration's)."""
        pred, drift, goal = carry
        track = pl.make_track(route, pred, opts.end_cap)
        tab = bound_tables(vp, pred, dt, opts, params)
        d = jnp.diff(jnp.interp(pl.step_bounds(pred), drift.s, drift.dE))  # (T,) per step
        bp = bound_dp(vp, pred, tab.with_drift(d), goal, opts.dp_n_E, opts.dp_penalty)
        mode, gear = bp.state // n_g, bp.state % n_g
        pieces = bound_pieces(vp, pred.mask, bp.E, bp.E_end, d, goal, opts.dp_n_E)
        plan = make_plan(vp, mode, gear, bp.P_b, bp.lam, pred, dt, opts, pieces)
        res = _run_plan(vp, track, pred, plan, plant_steps(n_steps, opts), dt)
        extra = BoundExtra(fuel_dp_J=jnp.sum(bp.cost), E_end_dp_J=bp.E_end, E_goal_J=goal,
                           plan=plan)

        def feedback():
            w = jnp.take_along_axis(pt.shaft_speeds(vp, pred.v), gear[:, None], axis=1)[:, 0]
            miss = res.final.E_b - res.E_b0
            return (repredict_level3(route, vp, dt, n_steps, pred, mode, w),
                    plant_drift(pred, plan, res),
                    jnp.where(k >= 1, jnp.clip(goal - miss, 0.0, vp.E_b_max), goal))

        return _unless_last(k, opts.dp_attempts, feedback, carry), (res, bp.lam0, extra, pred)

    init = (pred0, no_drift(pred0), jnp.asarray(E0, dtype))
    _, (ress, lam_dps, extras, preds) = jax.lax.scan(attempt, init,
                                                     jnp.arange(opts.dp_attempts))
    # of the plant runs that end within half the charge tolerance of their start, the one of
    # least corrected fuel (else the one that ends closest to its start)
    miss = ress.final.E_b - ress.E_b0
    corrected = ress.final.tot.fuel + lam_dps * miss
    near = jnp.abs(miss) <= 0.005 * vp.E_b_max
    best = jnp.where(jnp.any(near), jnp.argmin(jnp.where(near, corrected, jnp.inf)),
                     jnp.argmin(jnp.abs(miss)))
    pick = lambda tree: jax.tree_util.tree_map(lambda x: x[best], tree)  # noqa: E731
    res, lam_dp, extra, pred = pick(ress), pick(lam_dps), pick(extras), pick(preds)
    return Run(_metrics(res, pred, vp, lam_dp, OK), res, pred, extra)


KERNELS = {
    "conventional": run_conventional,
    "baseline": run_baseline,
    "multilevel": run_multilevel,
    "multilevel-mpc": run_multilevel_mpc,
    "dp-bound": run_dp_bound,
    "multilevel-eco": run_multilevel_eco,
}


# ------------------------------------------------------------------------------ host API
def check_strategy(name: str) -> str:
    if not isinstance(name, str) or name not in KERNELS:
        raise ValueError(f"strategy: unknown {name!r} (choose from {', '.join(STRATEGIES)})")
    return name


def _kernel(strategy: str, dt: float, n_steps: int, opts: Options):
    fn = KERNELS[strategy]
    return lambda route, vp, params: fn(route, vp, dt, n_steps, opts, params)


# XLA's CPU code generator per strategy (`xla`; measured, README "Compilation"): the elemental
# emitters compile a run in up to 25 % less time and run it as fast, but the MPC and the
# eco-driving run 5-26 % slower with them and a batch of conventional trucks 3-30 % slower; those
# keep XLA's default emitters. The other batches run as fast in about half the memory.
SINGLE_ELEMENTAL = {name: name not in ("multilevel-mpc", "multilevel-eco") for name in STRATEGIES}
BATCH_ELEMENTAL = {name: SINGLE_ELEMENTAL[name] and name != "conventional" for name in STRATEGIES}


# the options whose values the programs take as arguments (weakly typed scalars, as the Python
# floats they were), so that a new value runs the program compiled for the last one: numbers
# that no shape, loop count or branch of the program depends on. The other options are
# compiled in (`Options`: structure, counts, switches, and the two that may be None).
TRACED_OPTIONS = ("lam0", "kp", "ke_share", "dwell", "ecms_horizon", "dp_penalty", "tau_E",
                  "eco_time_ratio", "eco_overspeed_kmh", "mpc_end_reserve", "end_reserve")


def split_options(opts: Options) -> tuple[Options, dict]:
    """(key, values): opts with its `TRACED_OPTIONS` at their defaults, the static key a
    program is compiled for, and those options' values (floats), its arguments; a program
    puts them back with `key._replace(**values)`."""
    values = {k: float(getattr(opts, k)) for k in TRACED_OPTIONS}
    return opts._replace(**{k: Options._field_defaults[k] for k in TRACED_OPTIONS}), values


def _run(route, vp, params, values, *, strategy, dt, n_steps, opts):
    return _kernel(strategy, dt, n_steps, opts._replace(**values))(route, vp, params)


_RUN = {e: jit(_run, elemental=e, static_argnames=("strategy", "dt", "n_steps", "opts"))
        for e in (True, False)}


def _run_one(route, vp, params, *, strategy, dt, n_steps, opts):
    """One run, compiled with the strategy's code generator (`SINGLE_ELEMENTAL`)."""
    key, values = split_options(opts)
    return _RUN[SINGLE_ELEMENTAL[strategy]](route, vp, params, values, strategy=strategy,
                                            dt=dt, n_steps=n_steps, opts=key)


@functools.lru_cache(maxsize=64)
def _item_fn(strategy: str, dt: float, n_steps: int, key: Options):
    """The metrics of one vehicle, with (route, switching params, `split_options`' values)
    shared: `shard.map_batch`'s item function (cached, so that repeated batches reuse one
    compilation; key: the options' static part)."""
    def item(shared, vp):
        route, params, values = shared
        return _kernel(strategy, dt, n_steps, key._replace(**values))(route, vp, params).metrics

    return item


_profile_batch = jit(jax.vmap(l3.velocity_profile, in_axes=(None, 0, 0)))


@functools.lru_cache(maxsize=16)
def _eco_trip_jit(dt: float, n_steps: int, key: Options):
    def trip(route, vp, values):
        return eco_speed(route, vp, dt, n_steps, key._replace(**values))[0].trip_time

    return jit(jax.vmap(trip, in_axes=(None, 0, None)))


def eco_trip_times(route, vehicles, dt: float, n_steps: int, opts: Options):
    """(B,) s: the trip times of multilevel-eco's speed profiles for a batch of vehicles."""
    key, values = split_options(opts)
    return _eco_trip_jit(float(dt), n_steps, key)(route, vehicles, values)


def steps_for_batch(route: Route, vehicles: VehicleParams, dt: float = 1.0,
                    strategy: str | None = None, options: Options | None = None) -> int:
    """Static Level 3 step count for a route and one vehicle or a batch (leading axis on every
    leaf): the longest trip, bucketed (`velocity.steps_for`). multilevel-eco drives its own
    profile: matched to Level 3's trip time (times eco_time_ratio, with the 0.5 % tolerance) or,
    with a given eco_lambda_t, as long as its optimum takes (computed here), and
    ECO_STEPS_MARGIN more."""
    if np.ndim(vehicles.mass) == 0:
        vehicles = stack_vehicles([vehicles])
    B, N = np.shape(vehicles.mass)[0], np.shape(route.grade)[-1]
    w = np.broadcast_to(np.asarray(vehicles.w_pred)[:, None], (B, N))
    prof = _profile_batch(route, vehicles, w)
    trip = float(jnp.max(prof.trip_time))
    n = l3.steps_for(trip, dt)
    if strategy == "multilevel-eco":
        o = options or Options()
        if o.eco_lambda_t is None:
            trip = trip * o.eco_time_ratio * (1.0 + 2.0 * l3.MATCH_RTOL)
        else:  # with a margin: the run's own optimisation (another program, another step
            # count) need not land on this one's optimum (a non-convex problem; at
            # eco_lambda_t = 0 in float32 on the short track 1683 s against 1513 here)
            eco = float(jnp.max(eco_trip_times(route, vehicles, dt, n, o)))
            trip = max(trip, eco * (1.0 + ECO_STEPS_MARGIN))
        n = max(n, l3.steps_for(trip, dt))
    return n


ECO_STEPS_MARGIN = 0.15  # `steps_for_batch`: multilevel-eco's steps beyond its optimum's trip


def _check_vehicle_batch(vehicles) -> int:
    """B, the batch size of `simulate_batch`'s vehicles: a `VehicleParams` whose every leaf
    has the same leading size B >= 1 (`shard._check_batch`); else a `VehicleError`."""
    if not isinstance(vehicles, VehicleParams):
        raise VehicleError(f"simulate_batch: vehicles must be a VehicleParams batch "
                           f"(stack_vehicles) (got {type(vehicles).__name__})")
    if np.ndim(vehicles.mass) != 1:
        raise VehicleError("simulate_batch: vehicles with one leading batch axis expected "
                           "(stack_vehicles; for one vehicle use simulate)")
    return shard._check_batch(vehicles, "simulate_batch", VehicleError)


def check_dt(dt) -> float:
    """The time step (s) as a float, from 0.05 to 10 s; else ValueError naming dt."""
    if not (isinstance(dt, numbers.Real) and not isinstance(dt, bool) and math.isfinite(dt)
            and 0.05 <= dt <= 10):
        raise ValueError(f"dt: must be a time step from 0.05 to 10 s (got {dt!r})")
    return float(dt)


def status_text(code: int) -> str:
    """'ok' or the names of the status flags joined by '+'."""
    names = [n for b, n in STATUS_NAMES.items() if int(code) & b]
    return "+".join(names) if names else "ok"


def _fields(m: Metrics, vp) -> dict:
    out = {k: np.asarray(getattr(m, k)) for k in Metrics._fields if k != "status"}
    out["fuel_l_per_100km"] = (np.asarray(pt.fuel_litres(vp, m.fuel_J))
                               / (np.asarray(m.length_m) / 1e5))
    out["fuel_corrected_J"] = out["fuel_J"] + out["lambda_b"] * out["delta_Eb_J"]
    out["status"] = np.array([status_text(c) for c in np.atleast_1d(np.asarray(m.status))])
    return out


# vehicles vmapped at once per device by default: the multilevel iteration runs Level 2's
# rounds and bisections until a chunk's slowest member is done, so small chunks waste less
# (LongHaul, 32 configurations of 1-8 MJ, 2 devices: 0.85 s of CPU per configuration in
# chunks of 4 against 1.08-1.11 s in chunks of 8 or 16), and a chunk of one runs unbatched
# (`shard.map_batch`), with plain while loops: 0.58-0.60 s against 0.65-0.69 in chunks of 4;
# the MPC, a Level 2 solve at every step, 17.5 s against 53-64 s in chunks of 1 (vmapped) or 2;
# multilevel-eco 10.1 s against 12.9 s in chunks of 4. Conventional and baseline run the
# plant's full Level 0 only at steps where some vehicle of the chunk needs it
# (`shard.shortcut`), so smaller chunks skip it more often: batch 256, chunks of 4 / 8 / 16 /
# 32 / 64 / 128, 103 / 126 / 132 / 119 / 119 / 107 configurations/s (conventional) and 83 /
# 113 / 113 / 92 / 80 / 81 (baseline). dp-bound: batch 8, chunks of 1 / 4 (vmapped), 0.527 /
# 0.525 configurations/s, compile 10.9 / 15.5 s, peak RSS 1.3 / 2.8 GB
# multilevel (2026-11-25): chunks of 4 vmapped, with Level 2 and the plan-keeping Level 1 one
# configuration at a time inside them (`shard.one_at_a_time`) and the plant vectorised: 5.57 /
# 5.55 configurations/s in chunks of 4 / 8 against 4.70 in chunks of one (batch 64)
CHUNK = {"multilevel": 4, "multilevel-mpc": 1, "multilevel-eco": 1, "dp-bound": 1,
         "conventional": 16, "baseline": 16}
assert set(CHUNK) == set(KERNELS), "every strategy has its chunk"
# On an accelerator (a GPU) a chunk's vehicles run in parallel and its steps one after the
# other, so a call's time hardly grows with the chunk until the device is full: multilevel on
# an H100, LongHaul, float32, chunks of the whole batch, 18.8 / 24.7 / 34.2 s a call for 256 /
# 1024 / 4096 configurations (13.6 / 41.4 / 119.9 configurations/s; docs/bench/gpu/). A chunk
# is then as large as a share of the device's memory allows. Device memory per configuration
# and Level 3 step in float32 (bytes): multilevel, conventional and baseline from their peaks
# on an H200 (2026-11-27, 43edbbe: 80 988 MiB at 8192, 5 734 and 366 MiB at 1024 configurations
# of 5376 steps: 1928, 1092 and 70 bytes; multilevel 1835 at 1024; on the H100 of 2026-11-24
# multilevel took about 1600 at 4096, on earlier code); the others from XLA's
# CPU buffer sizes (an upper bound: multilevel's is 4x its GPU peak)
ACCEL_BYTES_PER_STEP = {"multilevel": 1950, "conventional": 1100, "baseline": 70,
                        "multilevel-mpc": 820, "multilevel-eco": 5800, "dp-bound": 63000}
assert set(ACCEL_BYTES_PER_STEP) == set(KERNELS), "every strategy has its device memory"
ACCEL_MEMORY_SHARE = 0.6  # of the device's memory limit that a chunk may take
ACCEL_CHUNK = 1024  # where the device does not tell its memory


def device_memory(key: str = "bytes_limit") -> int | None:
    """A memory figure (bytes) of the default device's allocator: "bytes_limit", what it may
    use, or another key of `memory_stats` ("peak_bytes_in_use"); None on a CPU, or where the
    device does not say."""
    dev = jax.devices()[0]
    stats = dev.memory_stats() if dev.platform != "cpu" else None
    value = (stats or {}).get(key)
    return int(value) if value else None


def default_chunk(strategy: str, backend: str | None = None, n_steps: int = 5376,
                  itemsize: int = 4, memory: int | None = None) -> int:
    """`simulate_batch`'s chunk (vehicles vmapped at once per device) for ``chunk="auto"``.

    backend: "cpu", "gpu", ... (None: JAX's default backend). On a CPU the strategy's `CHUNK`;
    on an accelerator as many vehicles of `n_steps` Level 3 steps, in floats of `itemsize`
    bytes, as fit in `ACCEL_MEMORY_SHARE` of `memory` (bytes; None: `device_memory()`, and
    `ACCEL_CHUNK` where that is unknown), at `ACCEL_BYTES_PER_STEP`.
    """
    name = check_strategy(strategy)
    backend = jax.default_backend() if backend is None else backend
    if backend == "cpu":
        return CHUNK[name]
    memory = device_memory() if memory is None else memory
    if not memory:
        return ACCEL_CHUNK
    per_vehicle = ACCEL_BYTES_PER_STEP[name] * max(int(n_steps), 1) * itemsize / 4
    return max(1, int(ACCEL_MEMORY_SHARE * memory // per_vehicle))


def route_arg(route) -> Route:
    """A route argument of the API: a `Route` (checked, `route.check_route`: it may have been
    built or changed in Python) or a file path or bundled route name (loaded, and so checked;
    anything else is a TypeError naming `route`)."""
    return named_route(route)[1]


def named_route(route, name: str | None = None) -> tuple[str, Route]:
    """(the name results carry, the checked `Route`) of a route argument (`route_arg`): name,
    else the file's stem, else "route" for a `Route` built in Python."""
    if isinstance(route, Route):
        route = check_route(route)
        if np.ndim(route.ds) != 0:
            raise RouteError(f"route: one route expected (got a batch of {np.shape(route.ds)[0]} "
                             "routes: run them one at a time, or `sweep` them)")
        return name or "route", route
    if not isinstance(route, str | os.PathLike):
        raise TypeError(f"route: expected a Route, a file path or a bundled route's name (got "
                        f"{type(route).__name__})")
    from .io import load_route, route_name

    return name or route_name(route), load_route(route)


def simulate_batch(route: Route, vehicles: VehicleParams, strategy: str, dt: float = 1.0,
                   n_steps: int | None = None, options: Options | Mapping | None = None,
                   switching: sw.SwitchCostParams | None = None,
                   chunk: int | str | None = "auto", devices=None) -> dict[str, np.ndarray]:
    """Run one strategy for one route and a batch of vehicles in one jitted call.

    route: a `Route` or a path/bundled name (as `simulate`); vehicles: `VehicleParams` whose
    leaves all carry a leading batch axis B (`stack_vehicles`).
    n_steps: static Level 3 step count (`steps_for_batch`); pass the same value for every chunk
    of a route so that chunks share one compilation. The batch is split over `devices` (None:
    all of the default backend; on a CPU `shard.use_host_devices` makes one per core) and runs
    in vmapped chunks of at most `chunk` vehicles per device (None: all at once; "auto":
    `default_chunk`: a CPU's per-strategy chunk, or what an accelerator's memory holds), which
    bounds the memory (`shard.map_batch`). Returns (B,)
    arrays keyed as the JSON of `jaxems simulate` (less route, strategy, wall_s) plus
    `fuel_corrected_J` and `status`.
    """
    check_strategy(strategy)
    route = route_arg(route)
    _check_vehicle_batch(vehicles)
    check_vehicle(vehicles)
    if isinstance(chunk, str):
        if chunk != "auto":
            raise ValueError(f"chunk: an integer >= 1, None or 'auto' (got {chunk!r})")
    dt = check_dt(dt)
    opts = resolve_options(make_options(options, strategy), vehicles)
    params = sw.checked_params(switching, np.asarray(vehicles.mass).dtype)
    if n_steps is None:
        n_steps = steps_for_batch(route, vehicles, dt, strategy, opts)
    else:  # too few for a vehicle's Level 3 trip: its run's status says level3-steps-short
        # (checked in the program: a check here would run Level 3 once more for every chunk
        # of a sweep, 5 % of a conventional truck's time)
        if (isinstance(n_steps, bool) or not isinstance(n_steps, numbers.Integral)
                or not 1 <= n_steps <= MAX_STEPS):
            raise ValueError(f"n_steps: must be a whole number from 1 to {MAX_STEPS} (got "
                             f"{n_steps!r}; steps_for_batch gives what the trips need)")
        n_steps = int(n_steps)
    if chunk == "auto":
        chunk = default_chunk(strategy, n_steps=int(n_steps),
                              itemsize=np.asarray(vehicles.mass).dtype.itemsize)
    key, values = split_options(opts)
    fn = _item_fn(strategy, dt, int(n_steps), key)
    m = shard.map_batch(fn, vehicles, shared=(route, params, values), chunk=chunk,
                        devices=devices, elemental=BATCH_ELEMENTAL[strategy])
    return _fields(m, VehicleParams(*(np.asarray(x) for x in vehicles)))


@dataclass
class Result:
    """One simulated run: the JSON fields (`as_dict`), plus traces for plots and checks."""

    route: str
    strategy: str
    fields: dict
    trace: pl.Trace = field(repr=False)
    prediction: l3.Prediction = field(repr=False)
    plant: pl.PlantResult = field(repr=False)
    extra: Any = field(repr=False, default=None)

    def __getitem__(self, key):
        return self.as_dict()[key]

    def as_dict(self) -> dict:
        out = {"route": self.route, "strategy": self.strategy}
        for k, v in self.fields.items():
            v = np.asarray(v).reshape(-1)[0] if np.ndim(v) else v
            out[k] = v.item() if hasattr(v, "item") else v
        for k in ("mode_switches", "gear_switches"):
            out[k] = int(out[k])
        return out

    def trip_trace(self) -> pl.Trace:
        """The plant's trace over the trip's steps (those that start before its end; every step
        the plant ran where it did not reach the end), as NumPy arrays."""
        t_end = self["trip_time_s"]
        live = np.asarray(self.trace.t) < (t_end if np.isfinite(t_end) else np.inf)
        return jax.tree_util.tree_map(lambda x: np.asarray(x)[live], self.trace)

    def trace_columns(self) -> dict[str, np.ndarray]:
        """The plant's time series over the trip, one entry a step (the steps that start before
        the trip's end), as named columns with their units: at the step's start t_s, s_m,
        v_m_s, v_ref_m_s (Level 3's speed at that position) and E_b_J; over the step its mode
        (`powersplit.MODE_SHORT`: Mc, Me, Mm, Mo), gear (1 = first), the step's mean powers (W;
        P_d_W at the wheels, service brakes included; P_f_W the fuel power, idling included),
        lambda_b (the costate the controller applied), counted_s (what the run's totals count
        of the step, in s: dt, at the trip's end the share of the step up to the route's end)
        and the synchronisation energy of the step's switch (J) from the battery and from fuel,
        E_sync_b_J and E_sync_f_J, which the mean powers leave out: fuel_J is the sum of
        P_f_W counted_s + E_sync_f_J, and each step's E_b_J the last one's less its internal
        battery power (P_b_W + beta P_b_W^2) over counted_s and E_sync_b_J, within the
        battery's limits. The trip's end is in `as_dict` (trip_time_s, delta_Eb_J)."""
        tr = self.trip_trace()
        return {"t_s": tr.t, "s_m": tr.s, "v_m_s": tr.v, "v_ref_m_s": tr.v_ref, "E_b_J": tr.E_b,
                "mode": np.asarray(ps.MODE_SHORT)[tr.mode], "gear": tr.gear + 1,
                "P_d_W": tr.P_d, "P_e_W": tr.P_e, "P_m_W": tr.P_m, "P_b_W": tr.P_b,
                "P_f_W": tr.P_f, "P_brake_W": tr.P_brake, "lambda_b": tr.lam,
                "counted_s": tr.counted, "E_sync_b_J": tr.E_sync_b, "E_sync_f_J": tr.E_sync_f}



def simulate(route, vehicle="reference_truck", strategy: str = "multilevel", *,
             dt: float = 1.0, mass_kg: float | None = None, battery_MJ: float | None = None,
             initial_soc: float | None = None, options: Options | Mapping | None = None,
             switching: sw.SwitchCostParams | None = None, name: str | None = None,
             **option_kw) -> Result:
    """Simulate one strategy on one route with one vehicle; returns a `Result`.

    route: a `Route` or a path/bundled name; vehicle: `VehicleParams` or a name/path;
    mass_kg, battery_MJ, initial_soc: overrides (validated: positive, positive, in [0, 1]);
    options: `Options` (or its fields as keywords, e.g. n_iter=3, h1=5); switching:
    `SwitchCostParams` (None: the defaults; `switching.checked_params`). Bad options raise
    ValueError naming the option, and so does an option named here (a keyword or a dict's
    key) that the strategy does not depend on (`STRATEGY_OPTIONS`).
    """
    check_strategy(strategy)
    dt = check_dt(dt)
    opts = make_options(options, strategy, **option_kw)
    rname, route = named_route(route, name)
    vp = vehicle if isinstance(vehicle, VehicleParams) else load_vehicle(vehicle)
    vp = check_vehicle(with_overrides(vp, mass_kg=mass_kg, battery_MJ=battery_MJ,
                                      initial_soc=initial_soc))
    if np.ndim(vp.mass):
        raise VehicleError("simulate: one vehicle expected (use simulate_batch for a batch)")
    params = sw.checked_params(switching, np.asarray(vp.mass).dtype)
    opts = resolve_options(opts, vp)
    n_steps = steps_for_batch(route, vp, dt, strategy, opts)
    t0 = time.perf_counter()
    run = _run_one(route, vp, params, strategy=strategy, dt=dt, n_steps=n_steps, opts=opts)
    jax.block_until_ready(run)
    wall = time.perf_counter() - t0
    fields = _fields(run.metrics, vp)
    fields["wall_s"] = wall
    return Result(route=rname, strategy=strategy, fields=fields, trace=run.plant.trace,
                  prediction=run.pred, plant=run.plant, extra=run.extra)


def resolve_options(opts: Options, vehicles: VehicleParams) -> Options:
    """Options with `same_open_time` decided from the (concrete) vehicles when it is None;
    ValueError where it is True and a vehicle's dt_M and dt_G differ (Level 1's fast
    relaxation, which it selects, holds only for equal open times)."""
    if opts.same_open_time is False:
        return opts
    same = bool(np.all(np.asarray(vehicles.dt_M) == np.asarray(vehicles.dt_G)))
    if opts.same_open_time is None:
        opts = opts._replace(same_open_time=same)
    elif not same:
        raise ValueError("same_open_time=true: the vehicles' mode and gear open times differ "
                         "(switching.mode_open_s, gear_open_s); leave the option out, and it "
                         "is decided from the vehicles")
    return opts


def make_options(base: Options | Mapping | None = None, strategies=None, /,
                 **fields) -> Options:
    """`base` (None: the defaults; a dict: its fields) with `fields` replaced, checked:
    ValueError naming an unknown option or a bad value (the one check of `simulate`, sweep
    files and --option), and, given `strategies` (a name or a list), an option named here (a
    key of the dict or of `fields`; an `Options` base names none: it may serve several
    strategies) that none of them depends on (`check_options_used`)."""
    if isinstance(base, Mapping):  # the fields as a dict, as a sweep file's table gives them
        base, fields = None, {**base, **fields}
    elif base is not None and not isinstance(base, Options):
        raise TypeError(f"options: expected jaxems.strategies.Options or a dict of its fields "
                        f"(got {type(base).__name__})")
    bad = sorted(set(fields) - set(Options._fields))
    if bad:
        raise ValueError(f"unknown option {bad[0]!r} (options: {', '.join(Options._fields)})")
    # NumPy's whole numbers and reals as Python's (the options are static: a compilation's
    # key), the others as given for `_check_options` to judge
    fields = {k: (int(v) if isinstance(v, np.integer) else
                  float(v) if isinstance(v, np.floating) else v) for k, v in fields.items()}
    opts = (base or Options())._replace(**fields)
    _check_options(opts)
    if strategies is not None:
        check_options_used(strategies, fields)
    return opts


# the checks of `make_options`: whole numbers and their range (lo, hi); true/false options;
# real numbers, finite, with their range ((lo, hi, lo_open, hi_open); None: unbounded). The
# whole numbers size arrays or loops: above hi a run would not fit a machine's memory or would
# take hours (l2_pieces = 10**6 asked 9 TB of a (pieces x pieces) table on the short track),
# where the figures settle far below it (l2_pieces 32-64, dp_n_E 101-801, n_iter 2-4, h1 5-20)
_INT_OPTIONS = {"n_iter": (1, 20), "h1": (1, 600), "h2": (2, 86_400), "t2": (1, 3600),
                "dp_n_E": (11, 2001), "dp_lams": (2, 512),
                "l2_pieces": (1, 1024), "mpc_pieces": (1, 1024), "dp_attempts": (1, 20)}
_BOOL_OPTIONS = ("sustain", "guard_sides", "end_cap", "same_open_time", "level0_plan_power",
                 "trim_excursions")
_REAL_OPTIONS = {
    "lam0": (None, 0.0, False, True), "kp": (0.0, None, False, False),
    "dwell": (0.0, 3600.0, False, False), "ecms_horizon": (0.0, 3600.0, True, False),
    "soc_ref": (0.0, 1.0, False, False), "ke_share": (0.0, 1.0, False, False),
    "dp_penalty": (0.0, None, True, False), "plant_extra": (0.0, 10.0, False, False),
    "tau_E": (0.0, None, True, False), "eco_lambda_t": (0.0, None, False, False),
    "eco_time_ratio": (1.0, 1.5, False, False), "eco_overspeed_kmh": (0.0, 15.0, False, False),
    "mpc_end_reserve": (0.0, 1.0, False, False),
    "end_reserve": (0.0, 1.0, False, False),
}
_MAY_BE_NONE = ("soc_ref", "same_open_time", "eco_lambda_t")

# the options each strategy's run depends on (`check_options_used`): the plant's; those of a
# plan run on the plant (multilevel's, multilevel-eco's and dp-bound's; conventional's plan
# reads them too, but with no battery they change nothing); the iteration's
_PLANT_OPTIONS = ("plant_extra", "end_cap", "same_open_time")
_PLAN_OPTIONS = ("tau_E", "level0_plan_power", "trim_excursions")
_ITERATION_OPTIONS = ("n_iter", "sustain", "guard_sides", "l2_pieces", "end_reserve",
                      *_PLAN_OPTIONS)
STRATEGY_OPTIONS = {
    "conventional": _PLANT_OPTIONS,
    "baseline": (*_PLANT_OPTIONS, "lam0", "kp", "soc_ref", "ke_share", "dwell",
                 "ecms_horizon"),
    "multilevel": (*_PLANT_OPTIONS, *_ITERATION_OPTIONS),
    "multilevel-mpc": (*_PLANT_OPTIONS, "h1", "h2", "t2", "mpc_pieces", "mpc_end_reserve",
                       "lam0"),
    "dp-bound": (*_PLANT_OPTIONS, *_PLAN_OPTIONS, "dp_n_E", "dp_lams", "dp_penalty",
                 "dp_attempts"),
    "multilevel-eco": (*_PLANT_OPTIONS, *_ITERATION_OPTIONS, "eco_lambda_t", "eco_time_ratio",
                       "eco_overspeed_kmh"),
}


def check_options_used(strategies, names) -> None:
    """ValueError naming the first option in `names` that none of `strategies` (a name or a
    list) depends on (`STRATEGY_OPTIONS`): set for a strategy that ignores it, it would
    change nothing (`n_iter` for baseline) and the user would not know."""
    strategies = [check_strategy(s) for s in
                  ([strategies] if isinstance(strategies, str) else strategies)]
    for k in names:
        if k in Options._fields and not any(k in STRATEGY_OPTIONS[s] for s in strategies):
            users = [s for s in STRATEGIES if k in STRATEGY_OPTIONS[s]]
            which = " or ".join(strategies) if len(strategies) < 3 else \
                f"{', '.join(strategies[:-1])} or {strategies[-1]}"
            raise ValueError(f"{k}: not an option of {which}, which would ignore it "
                             f"(an option of {', '.join(users)})")


def _check_options(o: Options):
    """ValueError naming the first bad option: its type (a whole number, true or false, a
    finite real number) or its range."""
    for k, (lo, hi) in _INT_OPTIONS.items():
        v = getattr(o, k)
        if not (isinstance(v, int) and not isinstance(v, bool) and lo <= v <= hi):
            raise ValueError(f"{k}: must be a whole number >= {lo} and <= {hi} (got {v!r})")
    for k in _BOOL_OPTIONS:
        v = getattr(o, k)
        if not (isinstance(v, bool) or (v is None and k in _MAY_BE_NONE)):
            raise ValueError(f"{k}: must be true or false (got {v!r})")
    for k, (lo, hi, lo_open, hi_open) in _REAL_OPTIONS.items():
        v = getattr(o, k)
        if v is None and k in _MAY_BE_NONE:
            continue
        real = isinstance(v, int | float | np.integer | np.floating) and not isinstance(v, bool)
        ok = real and math.isfinite(v)
        ok = ok and (lo is None or (v > lo if lo_open else v >= lo))
        ok = ok and (hi is None or (v < hi if hi_open else v <= hi))
        if not ok:
            bounds = [f"{'>' if lo_open else '>='} {lo:g}"] if lo is not None else []
            bounds += [f"{'<' if hi_open else '<='} {hi:g}"] if hi is not None else []
            none = " or None" if k in _MAY_BE_NONE else ""
            raise ValueError(f"{k}: must be a finite number {' and '.join(bounds)}{none} "
                             f"(got {v!r})")
