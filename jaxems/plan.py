"""Level 1's plan over the whole prediction, made to keep Level 2's battery plan, and the plan
the plant's Level 0 follows (the `multilevel` iteration's, and dp-bound's rollout).

- `level1`: Level 1 (Hamiltonians of every mode and gear, switching costs, the Viterbi DP)
  over the whole prediction at a costate trace.
- `sustaining_level1`: Level 1 that keeps Level 2's battery plan: on each Level 2 piece a
  constant shift of the costate found by bisection, and across a jump of the piece's energy
  the two sides' plans joined in time (`split_sides`, `join_steps`), as Level 2's I2b single
  switch.
- The plan's battery accounting as the plant moves the battery (`plan_energy`: open
  driveline, synchronisation; `battery_path`: within the battery's limits), each piece's
  error against its target (`piece_error`, `held_piece_error`), the residual trimmed on M_c's
  steps (`trim_battery_power`, `excursion_pieces`), and the `Plan` the plant runs
  (`make_plan`, `plan_controller`).
- Level 2's pieces as Level 1's targets (`piece_targets`, `guard_lambda`), made up for the
  battery drift the plant showed against the last plan (`plant_drift`, `compensate`).

Pure functions of one vehicle and one prediction; shapes in the docstrings ((T,) steps, (K,)
pieces).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any, NamedTuple

import jax
import jax.numpy as jnp

from . import plant as pl
from . import powertrain as pt
from .levels import battery as l2
from .levels import level1 as l1
from .levels import powersplit as ps
from .levels import velocity as l3

if TYPE_CHECKING:
    from .strategies import Options


def init_state(pred: l3.Prediction):
    """The state before step 0 for Level 1: open driveline at a standing start, else free."""
    standing = pred.v_ref[0] <= 0
    return jnp.where(standing, ps.MO, -1).astype(jnp.int32), jnp.zeros((), jnp.int32)


def level1(vp, pred, lam, dt, params, fast=None, trac=None, switch_costs=True, fixed=None,
           path_of=None):
    """Level 1 over the whole prediction at costate lam ((T,) or ()), from the state before
    step 0 that `init_state` gives: `level1.level1_kernel` on the prediction's demand, speed,
    gradient and mask (fast, trac, fixed, switch_costs, path_of: as it takes them).
    Returns `Level1Result`."""
    m0, g0 = init_state(pred)
    return l1.level1_kernel(vp, pred.P_d, pred.v, pred.grade, lam, dt, pred.mask, m0, g0,
                            params, fast, trac, switch_costs, fixed, path_of)


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


def split_sides(vp, dE_first, dE_then, pid, target, t0, t1, then_high, within, tol):
    """The time split of `sustaining_level1` on its two sides' plans joined: each piece runs
    the plan `first` (dE_first: (T,) its steps' energy changes) up to a step t_s and `then`
    after it, t_s in [t0, t1) (K,) found by bisection down to one step on the piece's end
    within the battery's limits (`held_piece_error`), where then_high (K,): `then` alone ends
    above the target; where within (K,), `then` alone ends within tol (J) of the target and
    t0 is where the joined end stays within tol of it, t1 where it does not.
    Returns the final (t0, t1) (K,)."""
    k = jnp.arange(dE_first.shape[0])

    def bis(_, c):
        t0, t1 = c
        m = (t0 + t1) // 2
        e = held_piece_error(vp, jnp.where(k < m[pid], dE_first, dE_then), pid, target)
        return narrow(t0, t1, m, jnp.where(within, jnp.abs(e) <= tol, (e > 0) == then_high))

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
    battery the limits hold least on the way; a candidate the limits hold more than that
    margin beyond the least held of them does not count as near. Where the charging side
    meets its piece's target only as the battery's upper limit holds it and the other side
    misses it (a piece that ends full, which the side that charges on every descent reaches
    by throwing its surplus away), the time split keeps as much of the other side as still
    meets the target (`split_sides`' `within`): from a full battery on the short track at 20
    t, the plan climbed on the engine and threw 1.7 MJ of recuperation away (8.50 MJ
    corrected, dp-bound 5.38; now 5.49). Where no DP comes within that margin of the
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
    tol = tol_rel * vp.E_b_max
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
        near = jnp.abs(errs) <= jnp.min(jnp.abs(errs), axis=0) + tol
        # of those, the ones the limits hold least (within tol): a plan that comes near only
        # as the battery's limits hold it (full, its surplus thrown away) does not count
        near = near & (hs <= jnp.min(jnp.where(near, hs, jnp.inf), axis=0) + tol)
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

    def split_at(held_err, held, t0, t1, sides, states, charge_first):  # (t0, t1, js)
        # of an order; where `then` is the charging side and meets the target only as the
        # battery's upper limit holds it (a piece that ends full: it charges on every descent
        # and throws the surplus away) and `first` misses it, as much of `first` as keeps
        # the target (at the lower limit too, where the discharging side empties the
        # battery early, the rule cost Urban Delivery at 20 t 0.8 % on the plant, against
        # -0.3 % at the upper limit alone)
        pick = lambda x: (jnp.where(charge_first, x[0], x[1]),  # noqa: E731
                          jnp.where(charge_first, x[1], x[0]))  # (first's, then's) (K,)
        (first_err, then_err), then_held = pick(held_err), pick(held)[1]
        within = (~charge_first & (jnp.abs(then_err) <= tol) & (then_held > tol)
                  & (jnp.abs(first_err) > tol))
        t0, t1 = split_sides(vp, *first_then(charge_first, sides[0], sides[1]), pid, target, t0,
                             t1, then_err > 0, within, tol)
        return t0, t1, join_steps(vp, pred, lam, dt, pid, start, end, t0, t1,
                                  *first_then(charge_first, states[0], states[1]))

    def split(held_err, held, t0, t1, sides, states):  # the time split on the sides' plans
        # in the order the scores prefer, unless its joins both fall back from the split
        # (Level 0 refuses the switch there) where the other order's do not
        pref = preferred(held)
        at_pref, at_other = (split_at(held_err, held, t0, t1, sides, states, cf)
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
        r = level1(vp, pred, lam_t, dt, params, fast, trac, phase == 4, fixed,
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
    r0 = jax.eval_shape(lambda: level1(vp, pred, lam, dt, params, fast, trac, True, fixed))
    out0 = (jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), r0),
            jnp.zeros((T,), dtype))
    c = jax.lax.fori_loop(0, p_final + 1, step,
                          (-half, half, scores, scores, start, end, jnp.stack([start, end]),
                           jnp.zeros((K,), bool), jnp.zeros((2, T), dtype),
                           jnp.zeros((2, T), jnp.int32), out0))
    return c[-1]