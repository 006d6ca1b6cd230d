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
is the host API and `simulate_batch` the batched one used by sweeps.
"""

from __future__ import annotations

import functools
import math
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
from .params import (
    VehicleError,
    VehicleParams,
    check_vehicle,
    load_vehicle,
    stack_vehicles,
    with_overrides,
)
from .route import Route, check_route
from .xla import jit

STRATEGIES = ("conventional", "baseline", "multilevel", "multilevel-mpc", "dp-bound",
              "multilevel-eco")
PAPER_STRATEGIES = STRATEGIES[:5]  # the rows of the paper's Table 8
HYBRID = ("baseline", "multilevel", "multilevel-mpc", "dp-bound", "multilevel-eco")

# status codes of a run (bit flags) and their names
OK, INFEASIBLE_ROUTE, UNFINISHED, ECO_TIME = 0, 1, 2, 4
STATUS_NAMES = {INFEASIBLE_ROUTE: "infeasible-route", UNFINISHED: "unfinished",
                ECO_TIME: "eco-trip-time-missed"}


class Options(NamedTuple):
    """Static options of the strategies (hashable; a change recompiles).

    n_iter: multilevel iterations (>= 1); h1: Level 1 MPC horizon (samples); h2: Level 2 MPC
    window (samples); t2: Level 2 MPC sample time (samples); lam0, kp, soc_ref, ke_share, dwell:
    baseline A-ECMS (ke_share: share of the kinetic energy its charge feedback counts as in the
    battery already; soc_ref: the charge it holds, as a fraction of E_b_max with that share
    counted, None: the trip's start, `ecms_params`; dwell: least steps between its switches);
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
    dwell: int = 3
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
    """What a run reports; scalars (one route, one vehicle). level2_status: the flags of the
    last plan's Level 2 (`levels.battery.STATUS_NAMES`; 0 converged, PIECES_EXHAUSTED: its
    `l2_pieces` ran out with the battery's limits still violated) for the strategies that
    iterate (multilevel, multilevel-eco); NO_LEVEL2 for the others."""

    length_m: Any
    trip_time_s: Any
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


class Plan(NamedTuple):
    """A plan indexed by Level 3 step: (T,) mode, gear, costate, battery power (W) and the
    battery energy the plan expects at the start of each step (J); k_E (1/s) is the gain of the
    battery power's feedback on the energy's deviation from the plan; level0 (bool ()):
    Level 0 counts only the plan's battery power below its energy (`Options`'s
    level0_plan_power, `plant.Command.level0_plan`)."""

    mode: Any
    gear: Any
    lam: Any
    P_b: Any
    E_ref: Any
    k_E: Any
    level0: Any


def plan_controller(plan: Plan, cstate, vp, obs: pl.Obs):
    """Follow a plan by position: request the state planned for the next step (I(k) = M(k+1))
    and the planned battery power, corrected by the battery energy's deviation from the plan
    (the plant is not the plan's model: switches open the driveline, speeds differ); the plant
    clips it to what the active state and the battery allow. Where the engine runs, the battery
    helps recover the reference speed after a switch only while its energy is at or above the
    plan's (else the engine's headroom does, more slowly): recovering on the battery below the
    plan drained it by what no plan sees (dp-bound on Regional Delivery ended 0.41 MJ low;
    with the rule 0.001 MJ, for a trip 0.6 % longer). In M_m the battery recovers it always
    (the plant's rule): held at the speed it had, the truck fell behind the reference in Urban
    Delivery's crawls for most of its 1.4 % longer trip."""
    T = plan.mode.shape[0]
    j1 = jnp.minimum(obs.j + 1, T - 1)
    P_b = plan.P_b[obs.j] + plan.k_E * (obs.E_b - plan.E_ref[obs.j])
    return cstate, pl.Command(mode=plan.mode[j1], gear=plan.gear[j1], lam=plan.lam[obs.j],
                              P_b=P_b, catch_up=obs.E_b >= plan.E_ref[obs.j],
                              level0_plan=plan.level0)


def plan_energy(vp, pred, mode, gear, dt):
    """The battery energy change (J) of each step of a plan on the path (mode, gear: (T,)), as
    a function of its battery power: P_b (T,) -> dE (T,), as the plant moves the battery.

    - Each switch draws its synchronisation energy (`plant.path_sync_energy`).
    - A switch opens the driveline (`plant.path_open_time`) in the step before the new state's:
      the plant asks for the next step's state (`plan_controller`), so it switches while still
      on the old state's step, and then runs the new state's step in full. For the open part of
      that step the battery delivers and recuperates nothing. Braking, the service brakes take
      the power the plan recuperated; driving, the speed lost is made up after the switch, by
      the battery into M_m (so its energy is only deferred) and by the engine into M_c and M_e
      (the plant holds the planned battery power there). Level 1's plan has full traction on
      every step; without this, its battery energy runs ahead of the plant's by what its
      downshifts while braking recuperate (RegionalDelivery: 2.6 MJ over 160 switches). Counted
      on the new state's step instead, each switch into M_c while driving drew the new step's
      planned battery power unseen (Urban Delivery, 20 t: the plant ended 4 % of the battery
      below the plan; counted here, 0.0 %).
    """
    sync = pl.path_sync_energy(vp, mode, gear, pred.v)
    f_open = jnp.clip(pl.path_open_time(vp, mode, gear) / dt, 0.0, 1.0)
    f_open = jnp.concatenate([f_open[1:], jnp.zeros_like(f_open[:1])])  # the step before
    mode_next = jnp.concatenate([mode[1:], mode[-1:]])
    deferred = (mode_next == ps.MM) & (pred.P_d > 0)
    keep = jnp.where(deferred, 1.0, 1.0 - f_open)

    def dE(P_b):
        return jnp.where(pred.mask, -pt.battery_internal(vp, P_b) * dt * keep - sync, 0.0)

    return dE


def steps_energy(vp, pred, mode, gear, P_b, dt):
    """(T,) battery energy change (J) of each step of a plan (mode, gear, P_b: (T,));
    `plan_energy`."""
    return plan_energy(vp, pred, mode, gear, dt)(P_b)


def piece_span(pid, K: int):
    """(first, last) (K,) int32: each piece's first and last step in pid (T,) (`piece_ids`);
    an empty piece has first T and last -1."""
    T = pid.shape[0]
    k = jnp.arange(T, dtype=jnp.int32)
    return (jnp.full((K,), T, jnp.int32).at[pid].min(k),
            jnp.full((K,), -1, jnp.int32).at[pid].max(k))


def target_bounds(vp, target):
    """(start, end) (K,): where the targets (K,) put each piece's start and end, E_b(t_0) plus
    the targets up to it, within the battery's limits (Level 2's plan, `battery_path`)."""
    dtype = target.dtype
    E_max = jnp.asarray(vp.E_b_max, dtype)
    cum = jnp.asarray(vp.soc0 * vp.E_b_max, dtype) + jnp.cumsum(target)
    return jnp.clip(cum - target, 0.0, E_max), jnp.clip(cum, 0.0, E_max)


def battery_path(vp, dE, pid, target):
    """The battery energy (J) a plan expects, piece by piece, within the battery's limits.

    dE: (T,) each step's energy change; pid: (T,) the piece of each step (non-decreasing);
    target: (K,) each piece's energy change (`piece_targets`). Each piece starts where the
    targets put it, E_b(t_0) plus the targets before it (Level 2's plan), and within it the
    energy is held in [0, E_b_max] as the plant holds it: recuperation beyond a full battery goes
    to the service brakes, an empty battery delivers nothing. Level 1 has no battery state: on
    a long descent its plan may recuperate more than the battery holds (a piece Level 2 marks
    saturated), elsewhere drain it below empty and recover before the piece ends; without the
    limits the plan's energy runs far outside what the plant can store, and the battery-power
    feedback chases it for the rest of the route.

    Returns (E: (T,) energy at the start of each step, E_end: (K,) at each piece's end, goal:
    (K,) where the targets put each piece's end, within the limits)."""
    dtype = dE.dtype
    E_max = jnp.asarray(vp.E_b_max, dtype)
    E0 = jnp.asarray(vp.soc0 * vp.E_b_max, dtype)
    starts, ends = target_bounds(vp, target.astype(dtype))
    first = jnp.concatenate([jnp.ones(1, bool), pid[1:] != pid[:-1]])

    def step(E, x):
        d, f, a = x
        E = jnp.where(f, a, E)
        E1 = jnp.clip(E + d, 0.0, E_max)
        return E1, (E, E1)

    _, (E, after) = jax.lax.scan(step, E0, (dE, first, starts[pid]))
    last = piece_span(pid, target.shape[0])[1]
    E_end = jnp.where(last >= 0, after[jnp.maximum(last, 0)], ends)
    return E, E_end, ends


def piece_error(dE, pid, target):
    """(K,) each piece's summed energy change minus its target (dE: (T,), pid: (T,),
    target: (K,), as `battery_path`)."""
    return l2.piece_sums(dE, pid, target.shape[0]) - target


def held_piece_error(vp, dE, pid, target):
    """(K,) each piece's end within the battery's limits minus where the targets put it
    (`battery_path`): what the plant, which holds the limits, would miss."""
    _, E_end, goal = battery_path(vp, dE, pid, target)
    return E_end - goal


def single_piece(T: int, dtype):
    """The whole route as one piece that ends where it starts (charge sustaining):
    (pid (T,), target (1,)) as `piece_targets` gives them."""
    return jnp.zeros(T, jnp.int32), jnp.zeros(1, dtype)


def narrow(a, b, m, pos, when=True):
    """One bisection step on brackets (a, b) with midpoint m: (m, b) where pos, else (a, m);
    unchanged where `when` is False."""
    return jnp.where(when & pos, m, a), jnp.where(when & ~pos, m, b)


def bisect_pieces(err, a, b, n: int, strict=True):
    """Bisection on every piece at once: err (K,) -> (K,) decreasing in x, brackets a, b: (K,).
    Keeps err(a) > 0 (strict; else >= 0) and err(b) <= 0 (< 0); returns the final (a, b)."""

    def bis(_, c):
        a, b = c
        m = 0.5 * (a + b)
        e = err(m)
        return narrow(a, b, m, jnp.where(strict, e > 0, e >= 0))

    return jax.lax.fori_loop(0, n, bis, (a, b))


def trim_battery_power(vp, pred, mode, gear, P_b, pid, target, dt, n_bisect: int = 40):
    """Battery power of a plan adjusted where the combined mode lets it move freely, so that the
    plan's energy change over each piece meets its target (pid: (T,), target: (K,), as
    `piece_targets`). Level 1's decisions move the battery in discrete steps (a climb on the
    motor or not); in M_c the engine and the motor share the demand continuously, so a plan's
    residual is spread there: on the M_c steps of piece p, P_b moves the fraction theta_p of the
    way to the top (theta_p > 0) or bottom (< 0) of the state's battery-power range, theta_p in
    [-1, 1] by bisection. The engine is affine in its power (Willans), so this costs about
    lambda_b per joule. A piece without M_c steps keeps its residual. Returns P_b: (T,)."""
    r = jax.vmap(lambda m, g, v: pl.state_ranges(vp, m, g, v))(mode, gear, pred.v)
    adj = pred.mask & (mode == ps.MC) & r.ok
    lo = jnp.minimum(ps.pb_engine_highest(vp, r, pred.P_d), P_b)
    hi = jnp.maximum(ps.pb_engine_lowest(vp, r, pred.P_d), P_b)
    K = target.shape[0]
    energy = plan_energy(vp, pred, mode, gear, dt)

    def P_of(theta):
        th = theta[pid]
        return jnp.where(adj, jnp.where(th > 0, P_b + th * (hi - P_b), P_b + th * (P_b - lo)),
                         P_b)

    def err(theta):  # decreases with theta (more discharge)
        return piece_error(energy(P_of(theta)), pid, target)

    def err_held(theta):  # the same within the battery's limits
        return held_piece_error(vp, energy(P_of(theta)), pid, target)

    one = jnp.ones((K,), P_b.dtype)
    theta = 0.5 * sum(bisect_pieces(err, -one, one, n_bisect))
    # where the plan leaves the battery's limits within a piece, the plant holds the energy
    # there and the piece misses its end: move theta on, as little as meets it within the
    # limits; where no theta meets it (the limit reached late in the piece decides its end),
    # as little as comes within 0.1 % of the battery of the range's end. Leaving theta where
    # the sum put it left the plant a piece's miss to carry into the next: on Regional
    # Delivery at 30 t with 4 MJ a piece from empty to empty ended 1.9 MJ high (0.34 MJ at
    # the range's end), the next piece's recuperation then filled the battery and the
    # service brakes took the rest
    e = err_held(theta)
    up = e > 0  # too much charge kept: discharge more (theta up), else less
    e_far = err_held(jnp.where(up, one, -one))
    reach = jnp.where(up, e_far <= 0, e_far >= 0)
    tol = 1e-3 * vp.E_b_max
    goal = jnp.where(reach, 0.0, e_far + jnp.where(up, tol, -tol))
    move = jnp.where(up, e > goal, e < goal)
    a, b = bisect_pieces(lambda th: err_held(th) - goal, jnp.where(up, theta, -one),
                         jnp.where(up, one, theta), n_bisect, up)
    return P_of(jnp.where(move, jnp.where(up, b, a), theta))


def excursion_pieces(vp, dE, pid, target, share: float = 0.01):
    """A plan's pieces (pid (T,), target (K,), as `piece_targets`) for its battery-power trim,
    each split in two where the plan's own path leaves the battery's limits furthest.

    From where the targets put a piece's start (`battery_path`), the path of the plan's steps
    dE (T,) without the limits; where it lies beyond them by more than `share` of the battery
    at the end of a step before the piece's last, the first part ends at that step, at
    clip(goal - what the rest of the piece's steps add, 0, E_b_max) (goal: where the targets
    put the piece's end): at the limit it left where the piece's steps meet its target, inside
    the limits where the rest cannot reach the goal from the limit. The second part takes the
    rest of the target.

    Why: trimmed over a whole piece (one theta on all its M_c steps, `trim_battery_power`), a
    plan whose path runs below empty within the piece and recovers before its end meets the
    piece's end, but asks energy of an empty battery on the way, which the plant cannot give:
    its engine covers it there, outside the plan's split (multilevel on Long Haul, 40 t, 8 MJ:
    17.8 MJ asked on 379 steps, the plant 46 MJ above the plan's Level 1 fuel; split, 12.5 MJ
    on 272 steps, 38 MJ). Above full, the recuperation beyond it goes to the service brakes.
    Split, the trim draws less before the excursion and more after it (or the reverse), where
    M_c steps allow. Split once: a second split of the parts gained nothing over the demo
    sweep's grid and left Urban Delivery at 20 t 5 % of the battery low.

    Returns (pid (T,), target (2K,)): piece p's parts are 2p and 2p + 1 (the second without
    steps where p is not split)."""
    dtype = dE.dtype
    E_max = jnp.asarray(vp.E_b_max, dtype)
    K = target.shape[0]
    T = dE.shape[0]
    k = jnp.arange(T, dtype=jnp.int32)
    starts, goal = target_bounds(vp, target)
    C = jnp.cumsum(dE)
    first, last = piece_span(pid, K)
    before = (C - dE)[jnp.clip(first, 0, T - 1)]  # (K,) the cumulative sum before each piece
    E = starts[pid] + C - before[pid]  # (T,) the free path at each step's end
    beyond = jnp.maximum(-E, E - E_max)  # > 0 beyond a limit
    worst = jnp.full((K,), -jnp.inf, dtype).at[pid].max(beyond)
    t_s = jnp.full((K,), T, jnp.int32).at[pid].min(jnp.where(beyond >= worst[pid], k, T))
    split = (worst > share * E_max) & (t_s < last)
    second = split[pid] & (k > t_s[pid])
    s2 = l2.piece_sums(jnp.where(second, dE, 0.0), pid, K)  # what the second part adds
    t1 = jnp.where(split, jnp.clip(goal - s2, 0.0, E_max) - starts, target)
    new_pid = 2 * pid + second.astype(pid.dtype)
    return new_pid, jnp.stack([t1, target - t1], axis=1).reshape(2 * K)


def make_plan(vp, mode, gear, P_b, lam, pred, dt, opts: Options, pieces=None) -> Plan:
    """A `Plan` from decisions (mode, gear, P_b: (T,)) and the costate, its battery power
    trimmed to the pieces' targets (`trim_battery_power`; default: charge sustaining), given
    pieces split where the plan leaves the battery's limits (`excursion_pieces`) if
    opts.trim_excursions.

    The battery energy it expects (E_ref) is its own steps' from the start, within the
    battery's limits, as the plant would follow them: not restarted at each piece where the
    targets put it. A piece the plan misses (its decisions cannot reach the end Level 2 set)
    leaves the plant where the plan leaves it; restarted, E_ref jumped there, the plant's
    battery-power feedback chased the jump and the iteration took the plan's own miss for
    the plant's drift (Regional Delivery, 30 t, 4 MJ: 1.9 MJ at a piece's start; 0.34 MJ
    with the trim at its range's end)."""
    lam = jnp.broadcast_to(lam, pred.v.shape)
    whole = single_piece(lam.shape[0], lam.dtype)
    pid, target = pieces if pieces is not None else whole
    energy = plan_energy(vp, pred, mode, gear, dt)
    if opts.trim_excursions and pieces is not None:
        pid, target = excursion_pieces(vp, energy(P_b), pid, target)
    P_b = trim_battery_power(vp, pred, mode, gear, P_b, pid, target, dt)
    return Plan(mode=mode, gear=gear, lam=lam, P_b=P_b,
                E_ref=battery_path(vp, energy(P_b), *whole)[0],
                k_E=jnp.asarray(1.0 / opts.tau_E, lam.dtype),
                level0=jnp.asarray(opts.level0_plan_power))


def guard_lambda(c2: l2.CostateResult, tol, gap: float = 0.05):
    """(T,) costate for Level 1 that carries Level 2's switching sequence at the guards (I2b).

    At a guard B1/B2 both sides have (nearly) the same lambda_b but different battery paths;
    Level 1, which sees switching costs, would pick one side for long stretches and leave the
    battery far from Level 2's path. Where a piece of Level 2's solution sits on a jump, lambda_b
    is moved `gap` to the side Level 2's I2b sequence is on at each step (B+: more negative,
    charging; B-: less negative), so that Level 1 follows the sequence; elsewhere it is Level
    2's costate unchanged."""
    T = c2.lam.shape[0]
    K = c2.lam_lo.shape[0]
    pid = l2.piece_ids(c2.boundaries, T)
    jump = jnp.abs(l2.piece_sums(c2.dE_plus - c2.dE_minus, pid, K)) > tol
    lam_lo, lam_hi = c2.lam_lo[pid], c2.lam_hi[pid]
    side = jnp.where(c2.sel > 0.5, lam_lo - gap, lam_hi + gap)
    return jnp.clip(jnp.where(jump[pid], side, c2.lam), l2.LAM_BRACKET[0], l2.LAM_BRACKET[1])


def piece_targets(c2: l2.CostateResult, T: int):
    """Level 2's pieces as Level 1 targets: pid (T,) the piece of each step, and dE (K,) the
    battery energy change (J) Level 2 plans over each piece (between its limits, or to the end
    of the route); pieces beyond `n_pieces` have no steps."""
    return l2.piece_ids(c2.boundaries, T), c2.E_bnd[1:] - c2.E_bnd[:-1]


class Drift(NamedTuple):
    """The plant's battery energy minus the plan's, by position: s (T+1,) positions (m, the
    plan's step starts and the route's end) and dE (T+1,) the deviation (J) there."""

    s: Any
    dE: Any


def no_drift(pred) -> Drift:
    T = pred.v.shape[0]
    return Drift(s=jnp.linspace(0.0, 1.0, T + 1, dtype=pred.v.dtype) * pred.length,
                 dE=jnp.zeros(T + 1, pred.v.dtype))


def plant_drift(pred, plan: Plan, res: pl.PlantResult) -> Drift:
    """How far the plant's battery energy fell from the plan's along the route: the switches
    the plant adds (stops, protection), the energy the open driveline costs and the speeds it
    drives move the battery in ways the plan's model does not see."""
    s = pl.step_bounds(pred)
    s_plant = jnp.concatenate([res.trace.s, res.final.s[None]])
    E_plant = jnp.concatenate([res.trace.E_b, res.final.E_b[None]])
    E_ref = jnp.concatenate([plan.E_ref, plan.E_ref[-1:]])
    return Drift(s=s, dE=jnp.interp(s, s_plant, E_plant) - E_ref)


def compensate(pieces, pred, bnd, drift: Drift):
    """Piece targets that make up for a plant drift measured on an earlier run: each piece's
    energy change is raised by what the plant lost over the same stretch of road. bnd: (K+1,)
    step indices of the piece boundaries (padded with T)."""
    pid, target = pieces
    s_b = pl.step_bounds(pred)[jnp.clip(bnd, 0, pred.v.shape[0])]
    d = jnp.interp(s_b, drift.s, drift.dE)
    return pid, target - (d[1:] - d[:-1])


def _split_bisections(T: int) -> int:
    """Bisection steps of `sustaining_level1`'s time split over T steps (down to one step)."""
    return int(math.ceil(math.log2(T + 1))) + 1


def _sustaining_phases(T: int, n_bisect: int) -> tuple[int, int, int]:
    """Where `sustaining_level1`'s phases start in its sequence of DPs over T steps: the two
    sides, the four candidates, the final plan (the shift's bisection starts at 0)."""
    p_side = n_bisect
    p_cand = p_side + 2
    return p_side, p_cand, p_cand + 4


def sustaining_dps(T: int, n_bisect: int = 14) -> int:
    """Full-route Level 1 DPs one `sustaining_level1` call runs over T steps: the shift's
    bisection, the two sides, the four candidates, the final plan."""
    return _sustaining_phases(T, n_bisect)[-1] + 1


def split_sides(vp, dE_first, dE_then, pid, target, t0, t1, then_high):
    """The time split of `sustaining_level1` on its two sides' plans joined: each piece runs
    the plan `first` (dE_first: (T,) its steps' energy changes) up to a step t_s and `then`
    after it, t_s in [t0, t1) (K,) found by bisection down to one step on the piece's end
    within the battery's limits (`held_piece_error`), where then_high (K,): `then` alone ends
    above the target. Returns the final (t0, t1) (K,)."""
    k = jnp.arange(dE_first.shape[0])

    def bis(_, c):
        t0, t1 = c
        m = (t0 + t1) // 2
        e = held_piece_error(vp, jnp.where(k < m[pid], dE_first, dE_then), pid, target)
        return narrow(t0, t1, m, (e > 0) == then_high)

    return jax.lax.fori_loop(0, _split_bisections(dE_first.shape[0]), bis, (t0, t1))


def join_steps(vp, pred, lam, dt, pid, start, end, t0, t1, s_first, s_then):
    """(2, K) where `sustaining_level1` joins its sides' plans as they are: each piece's t0 and
    t1 (K,) of the time split where Level 0 takes the switch there (from s_first's state before
    the step into s_then's at it, at the plan's demand and speed, the battery full: the plan's
    battery is judged by its held error, not here; `plant.requested_serves`), else the nearest
    step at or before t0 / at or after t1 whose predecessor both plans run in the same state
    (the piece's start or end at the latest), so that the joined path makes no switch that
    neither plan makes. On the short track at 20 t, joined mid-climb, a plan switched from M_e
    into M_m in gear 5, which after the open second could not pull the climb: the plant stayed
    in M_e for ten seconds and ended 1.2 MJ high. pid, s_first, s_then, lam: (T,); start, end
    (K,): each piece's first step and one past its last."""
    T = pid.shape[0]
    K = start.shape[0]
    k = jnp.arange(T)

    def taken(ts):  # (K,): Level 0 takes the switch at ts, or ts joins nothing mid-piece
        t = jnp.clip(ts, 1, T - 1)
        s_from, s_to, v = s_first[t - 1], s_then[t], pred.v[t]
        v_after = pl.speed_after_switch(vp, v, pt.road_load(vp, v, pred.grade[t]))
        ok = jax.vmap(lambda P, v, va, l, a, b: pl.requested_serves(
            vp, vp.E_b_max, P, v, va, l, a, b, v <= 0, jnp.inf, dt)[0])(
                jnp.maximum(pred.P_d[t], 0.0), v, v_after, lam[t], s_to, s_from)
        return ok | (s_from == s_to) | (ts <= start) | (ts >= end)

    prev = lambda x: jnp.concatenate([x[:1], x[:-1]])  # noqa: E731
    agree = (k == start[pid]) | (prev(s_first) == prev(s_then))
    j0 = jnp.full((K,), -1, jnp.int32).at[pid].max(
        jnp.where(agree & (k <= t0[pid]), k, -1).astype(jnp.int32))
    j1 = jnp.full((K,), T, jnp.int32).at[pid].min(
        jnp.where(agree & (k >= t1[pid]), k, T).astype(jnp.int32))
    return jnp.stack([jnp.where(taken(t0), t0, jnp.maximum(j0, start)),
                      jnp.where(taken(t1), t1, jnp.minimum(j1, end))]).astype(t0.dtype)


def sustaining_level1(vp, pred, lam, dt, params, pid, target, n_bisect: int = 14,
                      gap: float = 0.05, fast=None, tol_rel: float = 2.5e-3):
    """Level 1 that keeps Level 2's battery plan: on each Level 2 piece (pid: (T,) step ->
    piece, target: (K,) the piece's energy change) shift lambda_b(t) by a constant, found by
    bisection on all pieces at once, so that the DP's plan changes the battery by the piece's
    target (charge sustaining over the last piece; a limit reached where Level 2 reaches it).
    Where a piece's energy jumps with the shift (a guard, as in I2 of Level 2) the plans either
    side are joined in time within the piece: one side up to a step t_s and the other after
    (I2b's single switch), t_s found by bisection on the two sides' plans joined
    (`split_sides`: no DP; the DP of a joined costate mostly follows the joined plans, but its
    switching costs weigh the two sides together, and on Urban Delivery one piece's DP plan
    jumps by 1.6 MJ between neighbouring t_s; the candidates below are DPs). The side whose plan
    alone the battery's limits hold less goes first: where the plan's battery is held, the plant
    cannot do what the plan does (on the short track's first climb the discharging side first
    emptied the battery, and the plant then cruised on the engine where the plan cruised on the
    motor: 7.42 MJ corrected against 7.27 with the charging side first, on the plant before its
    mean gradient), unless Level 0 refuses the switch where that order joins them (both joins
    fall back from the split, `join_steps`) and takes it where the other order joins them: on
    the short track at 20 t with 4 MJ, the route one piece, the engine-first order joined
    mid-climb from M_e into M_m in gear 5, which Level 0 refuses, both joins fell back to the
    piece's ends, and the plan climbed on the motor alone, asking 0.42 MJ of an empty battery
    (the plant ended 6.3 % of the battery low, 10.4 % above dp-bound on corrected fuel); the
    motor first, the engine joins mid-climb (2.0 % low, 1.2 % above the bound). Each piece
    then takes, of the candidates (the bracket's ends of the shift
    and of the time split, each a DP) whose end comes closest to its target (within tol_rel
    E_b_max) with the battery held within its limits (`battery_path`: a plan that drains the
    battery below empty on the way ends higher in the plant than its sum says), the one whose
    battery the limits hold least on the way. Where no DP comes within that margin of the
    sides' plans joined at the split (at t0 or t1, where the plant's Level 0 takes the switch
    there, else where both run the same state: `join_steps`), the piece takes those, not a
    DP's: the final plan's DP runs at their costate there, and its path is replaced by theirs,
    so that the decisions, powers and switching costs (the switch where they join included)
    are Level 1's on that path. On Regional Delivery (20 t, the second
    iteration) the last piece's joined DPs ended 0.47 MJ above its target and its discharging
    side 0.39 MJ below, where the sides' plans joined came within 0.02 MJ: the plan then ended
    0.13 MJ short after its trim, and the plant 4.1 % of the battery low. Where Level 1's
    decisions move the battery in large steps (a whole climb on the motor or not) a residual
    remains. The plans' balances count what their switches cost the battery (`steps_energy`).
    Without Level 2 pieces (pid all 0, target (1,) = [0]) this is charge sustaining.
    Returns (Level1Result, lambda_b (T,) used)."""
    lo_b, hi_b = l2.LAM_BRACKET
    K = target.shape[0]
    T = pred.v.shape[0]
    k = jnp.arange(T)
    dtype = pred.v.dtype
    # the same for every lambda_b: the traction costs and the split of the modes without a
    # battery-power choice
    trac = l1.traction_table(vp, pred.v, pred.grade, params)
    fixed = ps.fixed_split(vp, pred.P_d, pred.v)
    # the DPs in order: the shift's bisection, the two sides, the four candidates, the final
    # plan; one loop with one DP in its body, so that the DP compiles once (at five call sites
    # the stage took about twice the compile time)
    p_side, p_cand, p_final = _sustaining_phases(T, n_bisect)

    def shifted(d):  # d: (K,) shift per piece
        return jnp.clip(lam + d[pid], lo_b, hi_b)

    start, last = piece_span(pid, K)
    end = last + 1

    def preferred(held):  # charge_first (K,): the side whose plan alone the limits hold
        # less goes first (per piece; `split` may turn it)
        return held[1] > held[0]

    def first_then(charge_first, x_a, x_b):  # (first, then) (T,) of the sides' x_a, x_b (T,)
        return (jnp.where(charge_first[pid], x_a, x_b), jnp.where(charge_first[pid], x_b, x_a))

    def joined(ts, first, then):  # (T,): `first` up to each piece's step ts (K,), `then` after
        return jnp.where(k < ts[pid], first, then)

    def choice(held_err, held):  # (K,) each piece's candidate, 0-5 (slots 2-7 of the scores)
        errs, hs = held_err[2:], held[2:]  # (6, K)
        near = jnp.abs(errs) <= jnp.min(jnp.abs(errs), axis=0) + tol_rel * vp.E_b_max
        # the sides' plans joined (4, 5) only where no DP (0-3) comes as near
        near = near & ((jnp.arange(6) < 4)[:, None] | ~jnp.any(near[:4], axis=0))
        return jnp.argmin(jnp.where(near, hs + 1e-3 * jnp.abs(errs), jnp.inf), axis=0)

    def costate(phase, i, a, b, charge_first, best, t0, t1, js):  # (T,) the costate of DP i
        # either side of the jump, shifted apart so that the DP, which weighs switching costs
        # over the whole horizon, follows each side in its own part of the piece
        ja, jb = shifted(a - gap), shifted(b + gap)
        first, then = first_then(charge_first, ja, jb)
        # the DPs' candidates (0-3), then the costates of the sides' plans joined where they
        # are joined (4, 5: `join_steps`), at which the final DP evaluates their path
        cands = jnp.stack([shifted(a), shifted(b)]
                          + [joined(t, first, then) for t in (t0, t1, js[0], js[1])])
        return jax.lax.select_n(phase, shifted(0.5 * (a + b)), ja, jb,
                                cands[jnp.clip(i - p_cand, 0, 3)], cands[best[pid], k])

    def final_path(phase, charge_first, best, js, states):  # the DP's path -> the plan's path
        # a piece whose candidate is the sides' plans joined takes their states (the final
        # DP's costate there is theirs, so its decisions and costs are the sides'; its
        # switching costs count the switch where they join)
        first, then = first_then(charge_first, states[0], states[1])
        use = (phase == 4) & (best >= 4)
        sides_path = joined(jnp.where(best == 4, js[0], js[1]), first, then)
        return lambda path: jnp.where(use[pid], sides_path, path)

    def split_at(held_err, t0, t1, sides, states, charge_first):  # (t0, t1, js) of an order
        then_high = jnp.where(charge_first, held_err[1], held_err[0]) > 0
        t0, t1 = split_sides(vp, *first_then(charge_first, sides[0], sides[1]), pid, target, t0,
                             t1, then_high)
        return t0, t1, join_steps(vp, pred, lam, dt, pid, start, end, t0, t1,
                                  *first_then(charge_first, states[0], states[1]))

    def split(held_err, held, t0, t1, sides, states):  # the time split on the sides' plans
        # in the order the scores prefer, unless its joins both fall back from the split
        # (Level 0 refuses the switch there) where the other order's do not
        pref = preferred(held)
        at_pref, at_other = (split_at(held_err, t0, t1, sides, states, cf)
                             for cf in (pref, ~pref))
        joins = lambda s: (s[2][0] == s[0]) | (s[2][1] == s[1])  # noqa: E731
        flip = ~joins(at_pref) & joins(at_other)
        t0, t1, js = jax.tree_util.tree_map(lambda x, y: jnp.where(flip, y, x), at_pref,
                                            at_other)
        charge_first = pref ^ flip
        first, then = first_then(charge_first, sides[0], sides[1])
        # the scores of the sides' plans joined there (slots 6, 7)
        dE = jnp.stack([joined(js[0], first, then), joined(js[1], first, then)])
        e = jax.vmap(lambda d: piece_error(d, pid, target))(dE)
        e_held = jax.vmap(lambda d: held_piece_error(vp, d, pid, target))(dE)
        return (t0, t1, js, flip, held_err.at[6:].set(e_held),
                held.at[6:].set(jnp.abs(e_held - e)))

    def step(i, c):
        a, b, held_err, held, t0, t1, js, flip, sides, states, _ = c
        # 0 the shift's bisection, 1 and 2 the sides, 3 the candidates, 4 the final plan
        phase = jnp.sum(i >= jnp.array([p_side, p_side + 1, p_cand, p_final]))
        # the time split once, before the candidates (`i` is not batched, so under vmap this
        # and the cond below stay conds)
        t0, t1, js, flip, held_err, held = jax.lax.cond(
            i == p_cand, split, lambda he, h, a, b, *_: (a, b, js, flip, he, h), held_err, held,
            t0, t1, sides, states)
        charge_first, best = preferred(held) ^ flip, choice(held_err, held)
        lam_t = costate(phase, i, a, b, charge_first, best, t0, t1, js)
        # the switching costs along the path only for the final plan, which returns them
        r = _level1(vp, pred, lam_t, dt, params, fast, trac, phase == 4, fixed,
                    final_path(phase, charge_first, best, js, states))
        dE = steps_energy(vp, pred, r.mode, r.gear, r.P_b, dt)
        e = piece_error(dE, pid, target)  # (K,) plan's energy change per piece minus target
        # within the battery's limits, as the plant holds them, and what the limits hold (the
        # shift's bisection needs neither)
        e_held = jax.lax.cond(phase == 0, lambda: e,
                              lambda: held_piece_error(vp, dE, pid, target))
        # the shift: a piece's dE decreases as its shift grows (cheaper battery: discharge)
        a, b = narrow(a, b, 0.5 * (a + b), e > 0, phase == 0)
        # the scores of the sides (slots 0, 1) and the candidates (2-5), the sides' plans
        side = (phase == 1) | (phase == 2)
        slot = jnp.where(side, i - p_side, i - p_cand + 2)
        keep = side | (phase == 3)
        held_err = jnp.where(keep, held_err.at[slot].set(e_held), held_err)
        held = jnp.where(keep, held.at[slot].set(jnp.abs(e_held - e)), held)
        s_slot = jnp.clip(slot, 0, 1)
        sides = jnp.where(side, sides.at[s_slot].set(dE), sides)
        states = jnp.where(side, states.at[s_slot].set(r.state), states)
        return a, b, held_err, held, t0, t1, js, flip, sides, states, (r, lam_t)

    half = jnp.full((K,), 1.5, dtype)
    scores = jnp.zeros((8, K), dtype)
    r0 = jax.eval_shape(lambda: _level1(vp, pred, lam, dt, params, fast, trac, True, fixed))
    out0 = (jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), r0),
            jnp.zeros((T,), dtype))
    c = jax.lax.fori_loop(0, p_final + 1, step,
                          (-half, half, scores, scores, start, end, jnp.stack([start, end]),
                           jnp.zeros((K,), bool), jnp.zeros((2, T), dtype),
                           jnp.zeros((2, T), jnp.int32), out0))
    return c[-1]


def _init_state(pred: l3.Prediction):
    """The state before step 0 for Level 1: open driveline at a standing start, else free."""
    standing = pred.v_ref[0] <= 0
    return jnp.where(standing, ps.MO, -1).astype(jnp.int32), jnp.zeros((), jnp.int32)


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
    return Metrics(
        length_m=pred.length, trip_time_s=t.trip_time, fuel_J=t.fuel,
        delta_Eb_J=res.final.E_b - res.E_b0,
        Eb_min_J=jnp.minimum(jnp.min(E), res.final.E_b),
        Eb_max_J=jnp.maximum(jnp.max(E), res.final.E_b),
        mode_switches=t.mode_switches, gear_switches=t.gear_switches,
        lambda_b=jnp.asarray(lam_b, E.dtype), max_speed_shortfall_mps=t.max_shortfall,
        status=jnp.asarray(status, jnp.int32),
        level2_status=jnp.asarray(level2, jnp.int32),
    )


def _level1(vp, pred, lam, dt, params, fast=None, trac=None, switch_costs=True, fixed=None,
            path_of=None):
    """Level 1 over the whole prediction (``fast``: `level1.solve_dp`'s static choice; trac:
    `level1.traction_table` and fixed: `powersplit.fixed_split` of the prediction, if at hand;
    switch_costs: `level1._result`'s; path_of: the path returned, from the DP's)."""
    m0, g0 = _init_state(pred)
    return l1._level1_full(vp, pred.P_d, pred.v, pred.grade, lam, dt, pred.mask, m0, g0, params,
                           fast, trac, switch_costs, fixed, path_of)


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
    r1 = _level1(vpc, pred, lam, dt, params, opts.same_open_time)
    plan = make_plan(vpc, r1.mode, r1.gear, r1.P_b, lam, pred, dt, opts)
    track = pl.make_track(route, pred, opts.end_cap)
    res = _run_plan(vpc, track, pred, plan, plant_steps(n_steps, opts), dt)
    return Run(_metrics(res, pred, vpc, 0.0, OK), res, pred, r1)


class EcmsParams(NamedTuple):
    lam0: Any
    kp: Any
    soc_ref: Any
    ke_share: Any
    dwell: Any  # steps
    switch: sw.SwitchCostParams


def ecms_lambda(p: EcmsParams, vp, E_b, v):
    """A-ECMS costate from charge feedback (no preview): E_b (J) and the speed v (m/s) now."""
    soc = (E_b + p.ke_share * 0.5 * vp.mass * v**2) / vp.E_b_max
    return jnp.clip(p.lam0 + p.kp * (soc - p.soc_ref), l2.LAM_BRACKET[0], l2.LAM_BRACKET[1])


def ecms_controller(p: EcmsParams, cstate, vp, obs: pl.Obs):
    """One-step DP: the current Hamiltonian plus the switching cost from the current state,
    with a minimum dwell time between switches (as shift logic has), unless the current state
    cannot serve (the plant's protection then switches anyway)."""
    since = cstate  # steps since the last switch
    lam = ecms_lambda(p, vp, obs.E_b, obs.v)
    tab = ps.mode_gear_split(vp, obs.P_req, obs.v_op, lam)
    n_g = vp.gear_ratio.shape[-1]
    s_cur = obs.mode * n_g + obs.gear
    # (not `level1.braking_loss`: paid on the one step this DP sees, the recuperation lost to
    # a switch always outweighs the one step gained, and it would never switch into braking)
    C = sw.switch_cost_matrix(vp, obs.v_op, obs.grade, lam, p.switch)[s_cur]
    cost = jnp.where(tab.feasible, tab.H, jnp.inf).reshape(-1) + C
    i = jnp.argmin(cost)
    i = jnp.where(jnp.isfinite(cost[i]) & (since >= p.dwell), i, s_cur)
    since = jnp.where(i == s_cur, since + 1, 0).astype(since.dtype)
    return since, pl.Command(mode=i // n_g, gear=i % n_g, lam=lam, P_b=jnp.nan)


def ecms_params(vp, track: pl.Track, opts: Options, params) -> EcmsParams:
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
    return EcmsParams(lam0=jnp.asarray(opts.lam0), kp=jnp.asarray(opts.kp), soc_ref=soc_ref,
                      ke_share=jnp.asarray(opts.ke_share), dwell=jnp.asarray(opts.dwell),
                      switch=params)


def run_baseline(route, vp, dt, n_steps: int, opts: Options, params) -> Run:
    pred = level3(route, vp, dt, n_steps)
    track = pl.make_track(route, pred, opts.end_cap)
    p = ecms_params(vp, track, opts, params)
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
            r1, lam1 = _level1(vp, pred, lam_g, dt, params, opts.same_open_time), lam_g
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
    tb = l1._tables(vp, win1(p.P_d), win1(p.v), win1(p.grade), lam, p.dt, p.switch)
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
BIG = 1e15  # "infeasible" in the DP bound (finite, so that interpolation stays finite)


class BoundExtra(NamedTuple):
    """dp-bound's own figures: the DP's predicted fuel (J), its E_b(tf) (J, counting the plant
    drift it was given), the target it had, and the plan the plant ran (its rollout: mode,
    gear, the costate whose Level 1 split was chosen at each step, the trimmed battery
    power)."""

    fuel_dp_J: Any
    E_end_dp_J: Any
    E_goal_J: Any  # the DP's target E_b(tf): E_b(t0), moved by what the last attempt missed
    plan: Any  # `Plan`


def dp_candidate_lams(n: int):
    """Costate values whose Level 1 splits are dp-bound's battery-power candidates: (n,)."""
    return -jnp.exp(jnp.linspace(jnp.log(0.5), jnp.log(6.0), n))


def _on_grid(u, n_E):
    """Whether grid coordinate u lies on a grid of n_E points (within rounding)."""
    return (u >= -1e-9) & (u <= n_E - 1 + 1e-9)


def _interp_grid(x, dE, n_E):
    """Linear interpolation weights at x on a grid of n_E points dE apart: the lower point i0,
    the fraction f towards the next, and whether x is on the grid (`_on_grid`)."""
    u = x / dE
    i0 = jnp.clip(jnp.floor(u), 0, n_E - 2).astype(jnp.int32)
    return i0, u - i0, _on_grid(u, n_E)


class BoundCands(NamedTuple):
    """Battery-power candidates of some of dp-bound's states: fuel (J; BIG where infeasible),
    E_b change (J) and battery power (W), each (T, J, n) for n states with J candidates each,
    or (T, n) for n states with one candidate."""

    fuel: Any
    dEb: Any
    P_b: Any


class BoundTables(NamedTuple):
    """What dp-bound's DP needs of one vehicle on one prediction.

    dep: `BoundCands` (T, J, n_dep) of the first n_dep states, whose battery power depends on
    the costate (M_c's), at the J candidate costates lams: (J,); fix:
    `BoundCands` (T, S - n_dep) of the other states, whose split is the same at every costate
    (one candidate, `powersplit.fixed_split`); C: (T, S, S) Level 1's switching costs, priced at
    lam_sw: (T,) Level 2's costate; lam_end: () the worth of E_b(tf) beyond the goal (Level
    2's costate on its last piece). Kept apart, the fixed states' split is computed once
    instead of at every candidate costate (`full` joins them)."""

    dep: BoundCands
    fix: BoundCands
    C: Any
    lams: Any
    lam_end: Any
    lam_sw: Any

    def full(self) -> BoundCands:
        """Every state's candidates, (T, J, S) each: the fixed states' one repeated J times."""
        J = self.lams.shape[-1]

        def join(a, b):
            b = jnp.broadcast_to(b[..., None, :], b.shape[:-1] + (J, b.shape[-1]))
            return jnp.concatenate([a, b], axis=-1)

        return BoundCands(*(join(a, b) for a, b in zip(self.dep, self.fix, strict=True)))

    def with_drift(self, d):
        """The tables with d: (T,) added to every candidate's E_b change of each step."""
        return self._replace(dep=self.dep._replace(dEb=self.dep.dEb + d[:, None, None]),
                             fix=self.fix._replace(dEb=self.fix.dEb + d[:, None]))


class BoundPath(NamedTuple):
    """One DP of dp-bound to a goal: its (T,) state path, costate, step costs (J, with the
    switching costs), battery power and E_b at each step's start (J, the DP's model: with the
    drift its tables were given); E_b(tf) (J) and the costate at t0 (the slope of the value
    function at E_b(t0))."""

    state: Any
    lam: Any
    cost: Any
    P_b: Any
    E: Any
    E_end: Any
    lam0: Any


def bound_tables(vp, pred: l3.Prediction, dt, opts: Options, params) -> BoundTables:
    """`BoundTables`: M_c's split in every gear at opts.dp_lams costates
    (`dp_candidate_lams`), the other modes' once (`powersplit.fixed_split`), and the switching
    costs at Level 2's costate."""
    w0 = jnp.full_like(pred.v, vp.w_pred)
    c2 = l2.costate_kernel(vp, pred.P_d, pred.v, w0, pred.mask, dt)  # prices switching
    lam_sw = c2.lam
    lam_end = jnp.sum(jnp.where(l3.last_node(pred.mask), lam_sw, 0.0))
    lams = dp_candidate_lams(opts.dp_lams).astype(pred.v.dtype)
    # M_c alone chooses its battery power; the other modes' split is the same at every costate
    # (`powersplit.FIXED_MODES`). M_c's states come first (state = mode x n_gears + gear).
    assert ps.MC == 0 and ps.FIXED_MODES == (1, 2, 3), "M_c's states come first"

    def split_c(P_d, v, lam):  # M_c's (P_b, P_f, feasible), each (n_gears,)
        sp = ps.mode_gear_split(vp, P_d, v, lam, (ps.MC,))
        return sp.P_b[0], sp.P_f[0], sp.feasible[0]

    # (T, J, n_g) M_c's candidates; (T, S - n_g) the others' one
    c_dep = jax.vmap(lambda P_d, v: jax.vmap(lambda lam: split_c(P_d, v, lam))(lams))(
        pred.P_d, pred.v)
    fx = ps.fixed_split(vp, pred.P_d, pred.v)
    T = pred.v.shape[0]
    c_fix = (fx.P_b.reshape(T, -1), fx.P_f.reshape(T, -1), fx.feasible.reshape(T, -1))
    any_feas = jnp.any(c_dep[2], axis=(1, 2)) | jnp.any(c_fix[2], axis=1)

    def cands(Pb, Pf, feas):  # infeasible -> BIG cost; a step beyond capability: free
        some = any_feas.reshape((-1,) + (1,) * (Pb.ndim - 1))
        dEb = -pt.battery_internal(vp, Pb) * dt  # E_b increment
        return BoundCands(fuel=jnp.where(some, jnp.where(feas, Pf * dt, BIG), 0.0),
                          dEb=jnp.where(some, dEb, 0.0), P_b=Pb)

    def costs(P_d, v, g, lam, H):  # the switching costs of Level 1 (with what braking loses)
        return sw.switch_cost_matrix(vp, v, g, lam, params, l1.braking_loss(vp, H, P_d, dt))

    H_sw = ps.hamiltonian_H(vp, pred.P_d, pred.v, lam_sw, fx)  # (T, 4, G) at Level 2's costate
    Cs = jax.vmap(costs)(pred.P_d, pred.v, pred.grade, lam_sw, H_sw)  # (T, S, S)
    return BoundTables(dep=cands(*c_dep), fix=cands(*c_fix), C=Cs, lams=lams, lam_end=lam_end,
                       lam_sw=lam_sw)


def bound_dp(vp, pred: l3.Prediction, tab: BoundTables, goal, n_E: int,
             penalty) -> BoundPath:
    """The DP of dp-bound from E_b(t0) to E_b(tf) near goal over n_E E_b points x states.

    The states of tab.fix have one candidate, which the backward step reads once; the path is
    the one of the same tables `full` (their candidates repeated over the costates tie, and
    ties go to the first).

    Backward over the E_b grid with linear interpolation of the value function; its terminal
    cost lam_end (E - goal) + penalty |E - goal| keeps the value function nearly linear in E_b,
    where the interpolation is exact. A large kink alone (10 |E - goal|) is smeared by the
    interpolation wherever steps move E_b by less than a grid cell, which the DP then pays to
    avoid: on the short track its own corrected fuel moved 1.2 % between 101 and 401 points
    (0.05 % with the linear term). A forward rollout from the exact E_b(t0) gives the
    decisions."""
    dtype = pred.v.dtype
    E_max = vp.E_b_max
    dE = E_max / (n_E - 1)
    E_grid = jnp.arange(n_E, dtype=dtype) * dE
    E0 = vp.soc0 * E_max
    n_d = tab.dep.fuel.shape[-1]
    S = n_d + tab.fix.fuel.shape[-1]

    def q_of(V1, k_fuel, k_dE, E):
        """min over candidates of fuel + V1(E + dE): E (n,) -> (n, S) value, (n, S) arg."""
        x = E[:, None, None] + k_dE[None]  # (n, J, S)
        i0, f, inside = _interp_grid(x, dE, n_E)
        s_idx = jnp.arange(S)[None, None, :]
        v = (1 - f) * V1[i0, s_idx] + f * V1[i0 + 1, s_idx]
        tot = jnp.where(inside, k_fuel[None] + v, BIG)
        return jnp.min(tot, axis=1), jnp.argmin(tot, axis=1)

    def q_grid(V1, k_fuel, k_dE):
        """q_of's value at every grid point: (n_E, S) for V1 (n_E, S), k_fuel and k_dE (J, S)
        (any S and J). The grid is uniform, so a candidate
        (j, s) moves every point by the same u = dE_js / dE cells: its column of V1 is read
        as one contiguous slice from a copy padded with its end values (a slice per
        candidate, where q_of gathers every point; 1.5-1.8x faster per step) and weighted
        with one fraction. Points whose E_b + dE_js leaves the grid cost BIG, as in q_of."""
        u = k_dE / dE  # (J, S)
        o = jnp.floor(u)
        f = (u - o)[..., None]
        start = jnp.clip(o, -n_E, n_E - 1).astype(jnp.int32) + n_E  # (J, S) into the copy
        n_s = V1.shape[1]
        Vp = jnp.concatenate([jnp.broadcast_to(V1[:1], (n_E, n_s)), V1,
                              jnp.broadcast_to(V1[-1:], (n_E + 1, n_s))]).T  # (S, 3 n_E + 1)
        col = lambda s, i: jax.lax.dynamic_slice_in_dim(Vp[s], i, n_E + 1)  # noqa: E731
        sl = jax.vmap(jax.vmap(col), in_axes=(None, 0))(jnp.arange(n_s), start)  # (J, S, n_E+1)
        v = (1 - f) * sl[..., :-1] + f * sl[..., 1:]
        x = jnp.arange(n_E, dtype=dtype) + u[..., None]  # (J, S, n_E) grid coordinate
        return jnp.min(jnp.where(_on_grid(x, n_E), k_fuel[..., None] + v, BIG), axis=0).T

    m_init, g_init = _init_state(pred)
    s_init = jnp.where(m_init >= 0, m_init * (S // ps.N_MODES) + g_init, -1)

    def back(V1, inp):
        (f_dep, dE_dep), (f_fix, dE_fix), C, m = inp
        # the states in their parts: (J, n_d) and one candidate each of the others
        parts = [(V1[:, :n_d], f_dep, dE_dep), (V1[:, n_d:], f_fix[None], dE_fix[None])]
        Q = jnp.concatenate([q_grid(*p) for p in parts if p[0].shape[1]], axis=1)  # (n_E, S)
        best, _ = dp.relax_dense(Q.T, C.T)  # best[s_prev, i] = min_s C[s_prev, s] + Q[i, s]
        V = jnp.minimum(best.T, BIG)
        V = jnp.where(m, V, V1)
        return V, V1

    def fwd(carry, inp):
        E, s = carry
        V1, dep, fix, C, m = inp
        k_fuel, k_dE, k_Pb = tab._replace(dep=dep, fix=fix).full()  # (J, S) each: every state's
        Q, jarg = q_of(V1, k_fuel, k_dE, E[None])  # (1, S)
        sw_cost = jnp.where(s >= 0, C[jnp.maximum(s, 0)], 0.0)
        tot = Q[0] + sw_cost
        s1 = jnp.argmin(tot).astype(jnp.int32)
        j1 = jarg[0, s1]
        E1 = E + k_dE[j1, s1]
        cost = k_fuel[j1, s1] + sw_cost[s1]
        s1 = jnp.where(m, s1, jnp.maximum(s, 0))
        E1 = jnp.where(m, E1, E)
        return (E1, s1), (s1, tab.lams[j1], jnp.where(m, cost, 0.0), k_Pb[j1, s1], E)

    terminal = tab.lam_end * (E_grid - goal) + penalty * jnp.abs(E_grid - goal)
    V_T = jnp.broadcast_to(terminal[:, None], (n_E, S))
    V_0, V_next = jax.lax.scan(back, V_T, ((tab.dep.fuel, tab.dep.dEb),
                                           (tab.fix.fuel, tab.fix.dEb), tab.C, pred.mask),
                               reverse=True)
    # V_next[k] is the value after step k (before step k+1)
    (E_end, _), (path, lam_path, cost, Pb_path, E_path) = jax.lax.scan(
        fwd, (jnp.asarray(E0, dtype), s_init), (V_next, tab.dep, tab.fix, tab.C, pred.mask))
    i0, _, _ = _interp_grid(E0, dE, n_E)
    lam0 = _bound_costate(V_0[:, path[0]], i0, dE)
    return BoundPath(state=path, lam=lam_path, cost=cost, P_b=Pb_path, E=E_path, E_end=E_end,
                     lam0=lam0)


def _bound_costate(V, i0, dE):
    """The bound's lambda_b at the start: dV/dE_b of the value function V (n_E,) of the first
    state, on the grid interval [i0, i0 + 1] that holds E_b(t0), or on the one below where a
    point of it is (partly) infeasible (a full battery: its values there mix in BIG), within
    Level 2's bracket (a run started full at 200 MJ reported +4e7 before, and a corrected fuel
    of -4e12 J)."""
    clean = lambda i: V[jnp.clip(i, 0, V.shape[0] - 1)] < 1e-3 * BIG  # noqa: E731
    up = (V[i0 + 1] - V[i0]) / dE
    down = (V[i0] - V[jnp.maximum(i0 - 1, 0)]) / dE
    use_down = clean(i0) & ~clean(i0 + 1) & clean(i0 - 1) & (i0 > 0)
    return jnp.clip(jnp.where(use_down, down, up), *l2.LAM_BRACKET)


BOUND_PIECES = 64  # the most pieces of dp-bound's plan (`bound_pieces`), per 4096 steps


def bound_pieces(vp, mask, E, E_end, d, goal, n_E: int, K: int | None = None):
    """dp-bound's DP path as its plan's pieces (pid: (T,), target: (K,), as `piece_targets`
    gives Level 2's): a piece ends where the path reaches a limit of the battery or leaves it
    (within half a cell of the DP's E_b grid of n_E points), and its target is the DP's own
    change over it, without the drift d: (T,) its steps counted (`BoundTables.with_drift`);
    the last piece's is moved by goal - E_end, so that the plan ends where the DP was to. E:
    (T,) the DP's E_b at each step's start, E_end: its E_b(tf); mask: (T,) steps that count.
    From the K-th boundary on (default: BOUND_PIECES per 4096 steps, at least BOUND_PIECES;
    the demo grid's paths need at most 41 on Long Haul) the last piece takes the rest.

    With the whole route as one piece, the plan's trim (`trim_battery_power`) spread what the
    plan's own model (the switches' synchronisation energy and open driveline, which the DP's
    battery does not see) moved over all of its M_c steps, and where the path met the limits
    several times it met the end only by a plan held at empty for long stretches: on Long Haul
    (20 t, the first attempt) the trim moved the plan's battery by 18 MJ against the DP's, the
    plan asked for M_m with an empty battery for 2 km at a time, and the plant, which cannot,
    burned 9 MJ more than the DP's own model; the attempts' plant runs spread over 854-873 MJ
    (854.4-855.4 MJ with these pieces)."""
    if K is None:
        K = BOUND_PIECES * max(1, -(-E.shape[0] // 4096))
    tol = 0.5 * vp.E_b_max / (n_E - 1)
    at = mask & ((E <= tol) | (E >= vp.E_b_max - tol))
    edge = mask & (at != jnp.concatenate([at[:1], at[:-1]]))
    pid = jnp.minimum(jnp.cumsum(edge.astype(jnp.int32)), K - 1)
    E_next = jnp.concatenate([E[1:], jnp.reshape(E_end, (1,))])
    target = l2.piece_sums(jnp.where(mask, E_next - E - d, 0.0), pid, K)
    return pid, target.at[pid[-1]].add(goal - E_end)


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
    if name not in KERNELS:
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


def _run(route, vp, params, *, strategy, dt, n_steps, opts):
    return _kernel(strategy, dt, n_steps, opts)(route, vp, params)


_RUN = {e: jit(_run, elemental=e, static_argnames=("strategy", "dt", "n_steps", "opts"))
        for e in (True, False)}


def _run_one(route, vp, params, *, strategy, dt, n_steps, opts):
    """One run, compiled with the strategy's code generator (`SINGLE_ELEMENTAL`)."""
    return _RUN[SINGLE_ELEMENTAL[strategy]](route, vp, params, strategy=strategy, dt=dt,
                                            n_steps=n_steps, opts=opts)


@functools.lru_cache(maxsize=64)
def _item_fn(strategy: str, dt: float, n_steps: int, opts: Options):
    """The metrics of one vehicle, with (route, switching params) shared: `shard.map_batch`'s
    item function (cached, so that repeated batches reuse one compilation)."""
    f = _kernel(strategy, dt, n_steps, opts)
    return lambda shared, vp: f(shared[0], vp, shared[1]).metrics


_profile_batch = jit(jax.vmap(l3.velocity_profile, in_axes=(None, 0, 0)))


@functools.lru_cache(maxsize=16)
def _eco_trip_fn(dt: float, n_steps: int, opts: Options):
    return jit(jax.vmap(lambda route, vp: eco_speed(route, vp, dt, n_steps, opts)[0].trip_time,
                        in_axes=(None, 0)))


def steps_for_batch(route: Route, vehicles: VehicleParams, dt: float = 1.0,
                    strategy: str | None = None, options: Options | None = None) -> int:
    """Static Level 3 step count for a route and one vehicle or a batch (leading axis on every
    leaf): the longest trip, bucketed (`velocity.steps_for`). multilevel-eco drives its own
    profile: matched to Level 3's trip time (times eco_time_ratio, with the 0.5 % tolerance) or,
    with a given eco_lambda_t, as long as its optimum takes (computed here)."""
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
        else:
            trip = max(trip, float(jnp.max(_eco_trip_fn(float(dt), n, o)(route, vehicles))))
        n = max(n, l3.steps_for(trip, dt))
    return n


def check_dt(dt) -> float:
    """The time step (s) as a float, from 0.05 to 10 s; else ValueError naming dt."""
    if not (isinstance(dt, int | float) and math.isfinite(dt) and 0.05 <= dt <= 10):
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
        return name or "route", check_route(route)
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
    if np.ndim(vehicles.mass) != 1:
        raise VehicleError("simulate_batch: vehicles with one leading batch axis expected "
                           "(stack_vehicles; for one vehicle use simulate)")
    check_vehicle(vehicles)
    if isinstance(chunk, str):
        if chunk != "auto":
            raise ValueError(f"chunk: an integer >= 1, None or 'auto' (got {chunk!r})")
    dt = check_dt(dt)
    opts = resolve_options(make_options(options), vehicles)
    params = sw.checked_params(switching, np.asarray(vehicles.mass).dtype)
    if n_steps is None:
        n_steps = steps_for_batch(route, vehicles, dt, strategy, opts)
    if chunk == "auto":
        chunk = default_chunk(strategy, n_steps=int(n_steps),
                              itemsize=np.asarray(vehicles.mass).dtype.itemsize)
    fn = _item_fn(strategy, dt, int(n_steps), opts)
    m = shard.map_batch(fn, vehicles, shared=(route, params), chunk=chunk, devices=devices,
                        elemental=BATCH_ELEMENTAL[strategy])
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
    ValueError naming the option.
    """
    check_strategy(strategy)
    dt = check_dt(dt)
    opts = make_options(options, **option_kw)
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
    """Options with `same_open_time` decided from the (concrete) vehicles when it is None."""
    if opts.same_open_time is None:
        same = bool(np.all(np.asarray(vehicles.dt_M) == np.asarray(vehicles.dt_G)))
        opts = opts._replace(same_open_time=same)
    return opts


def make_options(base: Options | Mapping | None = None, /, **fields) -> Options:
    """`base` (None: the defaults; a dict: its fields) with `fields` replaced, checked:
    ValueError naming an unknown option or a bad value (the one check of `simulate`, sweep
    files and --option)."""
    if isinstance(base, Mapping):  # the fields as a dict, as a sweep file's table gives them
        base, fields = None, {**base, **fields}
    elif base is not None and not isinstance(base, Options):
        raise TypeError(f"options: expected jaxems.strategies.Options or a dict of its fields "
                        f"(got {type(base).__name__})")
    bad = sorted(set(fields) - set(Options._fields))
    if bad:
        raise ValueError(f"unknown option {bad[0]!r} (options: {', '.join(Options._fields)})")
    opts = (base or Options())._replace(**fields)
    _check_options(opts)
    return opts


# the checks of `make_options`: whole numbers and their range (lo, hi); true/false options;
# real numbers, finite, with their range ((lo, hi, lo_open, hi_open); None: unbounded). The
# whole numbers size arrays or loops: above hi a run would not fit a machine's memory or would
# take hours (l2_pieces = 10**6 asked 9 TB of a (pieces x pieces) table on the short track),
# where the figures settle far below it (l2_pieces 32-64, dp_n_E 101-801, n_iter 2-4, h1 5-20)
_INT_OPTIONS = {"n_iter": (1, 20), "h1": (1, 600), "h2": (2, 86_400), "t2": (1, 3600),
                "dp_n_E": (11, 2001), "dp_lams": (2, 512), "dwell": (0, 3600),
                "l2_pieces": (1, 1024), "mpc_pieces": (1, 1024), "dp_attempts": (1, 20)}
_BOOL_OPTIONS = ("sustain", "guard_sides", "end_cap", "same_open_time", "level0_plan_power",
                 "trim_excursions")
_REAL_OPTIONS = {
    "lam0": (None, 0.0, False, True), "kp": (0.0, None, False, False),
    "soc_ref": (0.0, 1.0, False, False), "ke_share": (0.0, 1.0, False, False),
    "dp_penalty": (0.0, None, True, False), "plant_extra": (0.0, 10.0, False, False),
    "tau_E": (0.0, None, True, False), "eco_lambda_t": (0.0, None, False, False),
    "eco_time_ratio": (1.0, 1.5, False, False), "eco_overspeed_kmh": (0.0, 15.0, False, False),
    "mpc_end_reserve": (0.0, 1.0, False, False),
    "end_reserve": (0.0, 1.0, False, False),
}
_MAY_BE_NONE = ("soc_ref", "same_open_time", "eco_lambda_t")


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
