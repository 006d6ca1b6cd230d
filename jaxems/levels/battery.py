"""Level 2: the battery costate lambda_b (paper section 5, eqs. 46-55, Figures 11-15).

Level 2 model (section 5, assumptions): the velocity profile is given (P_d, v per time step),
the gear follows from a prescribed gearbox input speed omega, mode switches are instantaneous
and free. Per step k the Hamiltonian (eq. 53)

    H_2 = P_f - lambda_b P_bi

is minimised over the four modes in the gear G_k by the Level 1 kernel of
`jaxems.levels.powersplit` (no physics is repeated here), which gives the battery power P_b,k
and  E_b(k+1) = E_b(k) - P_bi(P_b,k) dt  (eq. 52). What does not depend on lambda_b (the
modes' ranges, and fuel and battery power at the candidates other than the two stationary
points) is computed once per solve (`step_table`), so that each pass of a bisection evaluates
only the combined mode's stationary points and compares. Since dlambda_b/dt = 0 (eq. 54),
lambda_b is constant between constraint activations and the problem is a boundary value
problem in lambda_b alone.

Gear rule: at every step the gear is the one whose shaft speed (`powertrain.shaft_speeds`) is
nearest to omega_k (absolute difference in rad/s) among the gears in which some mode meets the
demand (feasibility does not depend on lambda_b). Where no gear meets the demand, the nearest
gear is kept, the step uses P_b = 0 and no fuel, and the status says `STEP_INFEASIBLE`.
Padded steps (mask False) contribute nothing. Ties in H go to the lowest mode index (combined
before engine-only before motor-only before open), as in `optimal_mode_gear`.

Monotonicity: for every step, P_bi*(lambda_b) is non-decreasing in lambda_b (parametric
minimisation of P_f + (-lambda_b) P_bi), so E_b(t_f) is non-increasing in lambda_b: a more
negative lambda_b makes battery energy dearer and the EMS discharges less. Bisection on a
bracket [lam_min, lam_max] (default [-6, -0.3], an argument) with a fixed number of iterations
inside jit finds the solution (it stops early where every bracket is one ulp wide: float32
needs about 28 halvings); at lam = -6 the EMS charges as hard as the motor allows, at -0.3
it discharges as hard as it can, so the bracket spans the reachable range of E_b(t_f).

I1 (section 5.1, battery limits): the horizon is a list of pieces with fixed boundary values
(start E_b0, end E_b_end, interior boundaries at E_min or E_max). All pieces are bisected
together, each with its own constant lambda_b (one pass over the T steps per iteration: the
per-step costate is gathered from the piece index, the end values are segment sums). While a
piece's trajectory leaves [E_min, E_max], its largest violation is split off: the violated
limit becomes the end value of the first and the start value of the second piece. Pieces are
independent between their boundaries, so every violating piece is split in the same round
(what splitting only the largest violation overall per round reaches after as many rounds as
splits); when fewer pieces remain than pieces violate, the largest violations go first. One
refinement of the paper's outline: when the violated stretch reaches back to the start of its
piece and that start is on the same limit (the constraint arc simply goes on), the start moves
forward to the violation instead of a new piece being added. Pieces at a guard count as
violating only when no I2b switching sequence within the limits exists (paper 5.2.2: "else a
switching sequence exists"). Pieces live in static arrays of `max_pieces` = K entries
(boundaries padded with T, empty pieces are no-ops), so the procedure is jit- and
vmap-compatible; rounds are a `lax.while_loop` bounded by 3K rounds and K pieces that stops
when nothing is violated (under vmap a batch runs until its last member is done). When the
bound is reached and a violation remains, the status gets `PIECES_EXHAUSTED` and the last
solution is returned as it is: E_b then leaves the limits by `max_violation`, nothing is
clipped silently. Known weakness: a small battery whose energy swings several times its size
at a guard can need more than K pieces (short pieces that each gain a few steps along an arc).

A piece that charges beyond E_max even at lam_max (recuperation larger than the battery, e.g. a
long descent) cannot end at its end value with any lambda_b: for such a piece (`SATURATED`) the
battery is held at E_max and the surplus goes to the service brakes (E_b is reflected at E_max,
E_b(k) = S(k) - max(0, max_{j<=k} S(j) - E_max) with S the free trajectory), and the bisection
acts on the end value of the reflected trajectory. A piece whose end value lies above what
lam_min reaches (demand the battery cannot support, e.g. a climb longer than the battery) is
`INFEASIBLE`.

I2 (section 5.2, guards B1/B2): at the end of the bisection the bracket [lo, hi] is ~1e-12
wide. The trajectory at lo is B^+ (more charge, E_b(t_f) high), at hi B^- (E_b(t_f) low). When
they differ by more than the tolerance, the target lies in a jump of E_b(t_f)(lambda_b): the
status gets `AT_GUARD` and the piece is solved by mixing the two (eq. 55, I2a):
r E^-(t_f) + (1 - r) E^+(t_f) = target. The mix is applied to every piece (off a guard it just
removes the last bisection residual), so the reported E_b ends exactly on target. I2b
(`minimal_switching`) chooses, instead of the infinite switching of I2a, a 0/1 selector per step
between the two trajectories with the fewest switches that keeps E_b within the limits and
ends on target.

I3 (section 5.3, limited horizon): `level2_horizon` picks the lambda_b that maximises the
smallest distance of E_b to its limits over a prediction window (bisection on the balance of
the two distances, both monotone in lambda_b), with the special cases I3a (a limit is hit
whatever lambda_b: solve the first sub-problem up to that event) and I3b (the window is on a
guard and the non-unique solutions span both limits: lambda_b on the guard).

Everything is written for ONE vehicle and ONE route; `costate_batch` and `costate_product`
vmap it. All quantities SI: W, J, s, m/s, rad/s.
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import powertrain as pt
from ..params import VehicleParams, check_vehicle
from ..xla import jit
from . import powersplit as ps
from .powersplit import mode_gear_split

# ----------------------------------------------------------------------------- status bit flags
OK = 0
INFEASIBLE = 1  # a piece's end value is out of reach (or its end misses the target)
AT_GUARD = 2  # the target lies in a jump of E_b(t_f)(lambda_b): solved by mixing (I2)
PIECES_EXHAUSTED = 4  # I1 used all K pieces and a limit is still violated
SATURATED = 8  # recuperation beyond E_max: E_b held at E_max, surplus to the service brakes
STEP_INFEASIBLE = 16  # some step has no mode in any gear that meets the demand
I3A = 32  # limited horizon: a limit is hit whatever lambda_b; first sub-problem solved
I3B = 64  # limited horizon: on a guard whose non-unique solutions span both limits

STATUS_NAMES = {
    INFEASIBLE: "infeasible",
    AT_GUARD: "at-guard",
    PIECES_EXHAUSTED: "pieces-exhausted",
    SATURATED: "saturated",
    STEP_INFEASIBLE: "step-infeasible",
    I3A: "I3a",
    I3B: "I3b",
}

LAM_BRACKET = (-6.0, -0.3)


def _tol_v(tol, dtype):
    """Slack on the limits: 1e-3 of the end tolerance in float64, 1e-1 in float32 (cumulative
    sums of T steps in float32 carry errors of a few J at tens of MJ)."""
    return tol * (1e-3 if jnp.finfo(dtype).eps < 1e-10 else 1e-1)


def status_names(code) -> list[str]:
    """The names of the flags set in a status code ([] means converged)."""
    code = int(code)
    return [name for bit, name in STATUS_NAMES.items() if code & bit]


# ------------------------------------------------------------------------------- the step model
class Level2Steps(NamedTuple):
    """Per-step solution of the Level 2 model at given costates; every field (T,).

    P_b: battery terminal power (W); dE: E_b increment -P_bi dt (J); E_f: fuel energy P_f dt
    (J); P_m: motor mechanical power (W); mode: mode index (0 Mc, 1 Me, 2 Mm, 3 Mo).
    """

    P_b: jax.Array
    dE: jax.Array
    E_f: jax.Array
    P_m: jax.Array
    mode: jax.Array


def select_gears(vp: VehicleParams, P_d, v, w, mask):
    """Gear per step from the prescribed gearbox input speed w (rad/s).

    P_d, v, w: (T,), mask: (T,) bool -> (gear (T,) int, 0-based; ok (T,) bool). The gear is the
    feasible one (some mode meets P_d) whose shaft speed is nearest to w; where none is
    feasible the nearest gear and ok = False (and ok = False on padded steps).
    """
    sp = jax.vmap(mode_gear_split, in_axes=(None, 0, 0, None))(vp, P_d, v, -2.0)
    feas = jnp.any(sp.feasible, axis=1)  # (T, G)
    dist = jnp.abs(pt.shaft_speeds(vp, v) - w[:, None])
    g_feas = jnp.argmin(jnp.where(feas, dist, jnp.inf), axis=-1)
    g_any = jnp.argmin(dist, axis=-1)
    any_feas = jnp.any(feas, axis=-1)
    gear = jnp.where(any_feas, g_feas, g_any)
    return gear, any_feas & mask


class StepTable(NamedTuple):
    """The Level 2 model of every step at its gear, the part that does not depend on lambda_b
    (`step_table`): what a pass at new costates reads instead of computing the split again
    (`level2_steps`, `table_pass`). Every field has a leading axis T.

    P_d: (T,) demand (W); combined, motor: `powersplit.Setup` of the combined and motor-only
    modes (the combined mode's stationary candidates depend on lambda_b); P_f_c, P_bi_c: (T, 6)
    fuel and internal battery power (W) of the combined mode's candidates that do not depend on
    lambda_b (`Setup.fixed`); P_bi_m: (T, 6) those of motor-only, whose fuel is P_f_m: (T,) for
    every candidate (none, or the idling engine's); P_f_e, P_f_o: (T,) the fuel of engine-only
    and open, whose battery power is 0; feasible: (T, 4) bool per mode.
    """

    P_d: jax.Array
    combined: ps.Setup
    motor: ps.Setup
    P_f_c: jax.Array
    P_bi_c: jax.Array
    P_bi_m: jax.Array
    P_f_m: jax.Array
    P_f_e: jax.Array
    P_f_o: jax.Array
    feasible: jax.Array


def _table_step(vp, P_d, v, gear):
    w = pt.shaft_speeds(vp, v)[gear]

    def one(mode):  # the mode's setup, and (P_f, P_bi) of its lambda-free candidates
        s = ps.mode_setup(vp, P_d, w, ps.ENGINE_CONNECTED[mode], ps.MOTOR_CONNECTED[mode],
                          gear == 0)
        pw = [ps.mode_powers(vp, s, P_d, c) for c in s.fixed]
        return (s, jnp.stack([x[3] for x in pw]),
                jnp.stack([pt.battery_internal(vp, x[0]) for x in pw]))

    (c, f_c, b_c), (e, f_e, _), (m, f_m, b_m), (o, f_o, _) = (one(i) for i in range(ps.N_MODES))
    # engine-only and open: the motor open, the interval is {0} and every candidate P_b = 0;
    # motor-only: the engine open, every candidate burns the same (`mode_powers`: idle)
    return StepTable(
        P_d=P_d, combined=c, motor=m, P_f_c=f_c, P_bi_c=b_c, P_bi_m=b_m, P_f_m=f_m[0],
        P_f_e=f_e[0], P_f_o=f_o[0],
        feasible=jnp.stack([c.feasible, e.feasible, m.feasible, o.feasible]),
    )


def step_table(vp: VehicleParams, P_d, v, gear) -> StepTable:
    """`StepTable` of the steps P_d, v, gear: (T,) (the gears of `select_gears`)."""
    return jax.vmap(_table_step, in_axes=(None, 0, 0, 0))(vp, P_d, v, gear)


def _table_one(vp, t: StepTable, ok, lam, dt) -> Level2Steps:
    """One step of the Level 2 model at costate lam: every mode's H minimised over the
    candidates of `powersplit._split_one` in its order (ties to the first), then over the modes
    (ties to the lowest index, as `optimal_mode_gear`)."""

    def evaluate(c):  # a stationary candidate of the combined mode: (P_b, P_f, P_bi)
        c, _, _, P_f = ps.mode_powers(vp, t.combined, t.P_d, c)
        return c, P_f, pt.battery_internal(vp, c)

    z = jnp.zeros_like(t.P_d)
    fixed_c = [(c, t.P_f_c[i], t.P_bi_c[i]) for i, c in enumerate(t.combined.fixed)]
    per_mode = (
        ps.candidates(fixed_c, [evaluate(c) for c in ps.stationary(vp, t.combined, lam)]),
        [(z, t.P_f_e, z)],
        # no fuel to trade: H = P_f_m - lam P_bi is least at an end of the interval or at the
        # loss parabola's vertex, all lambda-free (the stationary points, whose formulas trade
        # fuel, never beat them)
        [(c, t.P_f_m, b) for c, b in zip(t.motor.fixed, t.P_bi_m, strict=True)],
        [(z, t.P_f_o, z)],
    )
    # each mode's best candidate, then the best mode. At exact ties (a guard) XLA may evaluate
    # the comparisons once per output, rounding H = P_f - lam P_bi with or without a fused
    # multiply-add, so that the fields come from two candidates of equal H (as in
    # `mode_gear_split`; seen only with the table folded as a constant)
    best = [ps.running_min([(c, f, b, f - lam * b) for c, f, b in cands]) for cands in per_mode]
    P_b, P_f, P_bi, H, mode = ps.running_min(
        [(c, f, b, jnp.where(t.feasible[m], h, jnp.inf), jnp.int32(m))
         for m, (c, f, b, h) in enumerate(best)], key=3)
    use = ok & jnp.isfinite(H)
    P_b = jnp.where(use, P_b, 0.0)
    r = jax.tree.map(lambda a, b: jnp.where(mode == ps.MC, a, b), t.combined.r, t.motor.r)
    P_m = jnp.where(use & ((mode == ps.MC) | (mode == ps.MM)), ps.pm_of_pb(vp, r, P_b), 0.0)
    return Level2Steps(P_b=P_b, dE=-jnp.where(use, P_bi, 0.0) * dt,
                       E_f=jnp.where(use, P_f, 0.0) * dt, P_m=P_m, mode=mode)


def steps_of_table(vp: VehicleParams, tab: StepTable, ok, lam, dt) -> Level2Steps:
    """`Level2Steps` at costate lam: () or (T,) from the steps' `StepTable`; ok: (T,) bool."""
    lam = jnp.broadcast_to(lam, jnp.shape(ok))
    return jax.vmap(_table_one, in_axes=(None, 0, 0, 0, None))(vp, tab, ok, lam, dt)


def level2_steps(vp: VehicleParams, P_d, v, gear, ok, lam, dt) -> Level2Steps:
    """Solve the Level 2 model step by step at costate lam: () or (T,). P_d, v, gear, ok: (T,).
    The minimisation is `powersplit.mode_gear_split`'s at the step's gear, its lambda-free part
    computed once (`step_table`), so that a bisection's passes (`table_pass`) evaluate only the
    combined mode's two stationary points and compare (0.11 against 0.26 ms a pass over
    LongHaul, float32, 4 configurations vmapped, one core)."""
    return steps_of_table(vp, step_table(vp, P_d, v, gear), ok, lam, dt)


def table_pass(vp: VehicleParams, tab: StepTable, ok, lam, dt):
    """(dE, E_f) of `steps_of_table` (the rest is not computed)."""
    s = steps_of_table(vp, tab, ok, lam, dt)
    return s.dE, s.E_f


class StepModel(NamedTuple):
    """Level 2's steps at their gears: gear, ok (`select_gears`) and their `StepTable`; a
    receding horizon slices the whole route's (the selection and the table are step by
    step)."""

    gear: jax.Array
    ok: jax.Array
    table: StepTable


def step_model(vp: VehicleParams, P_d, v, w, mask, gears=None) -> StepModel:
    """`StepModel` of the steps; gears: (gear, ok) or a `StepModel` already at hand."""
    if isinstance(gears, StepModel):
        return gears
    gear, ok = select_gears(vp, P_d, v, w, mask) if gears is None else gears
    return StepModel(gear, ok, step_table(vp, P_d, v, gear))


# --------------------------------------------------------------------------- piecewise helpers
def piece_ids(bnd, T):
    """Piece index of each step: bnd (K+1,) sorted, padded with T -> (T,) in [0, K-1]. Each
    step is compared with every boundary (few), one fused kernel where a binary search is a
    loop."""
    K = bnd.shape[0] - 1
    pid = jnp.searchsorted(bnd, jnp.arange(T), side="right", method="compare_all") - 1
    return jnp.clip(pid, 0, K - 1)


def piece_sums(x, pid, K: int):
    """(K,) the sum of x (T,) over each piece; pid (T,) the piece of each step, non-decreasing
    in [0, K) (`piece_ids`); an empty piece sums to 0.

    The sums are differences of one cumulative sum at the pieces' ends, in an order the program
    fixes: a float scatter-add (`jax.ops.segment_sum`) runs on a GPU as atomic additions in no
    fixed order, so its sums, and the bisections' decisions on them, differed between places
    of a batch and between runs. They round as the pieces' paths do (`_piece_paths`)."""
    C = jnp.concatenate([jnp.zeros((1,), x.dtype), jnp.cumsum(x)])
    n = jnp.zeros((K,), jnp.int32).at[pid].add(1)  # steps per piece (integer: exact)
    ends = jnp.cumsum(n)
    return C[ends] - C[ends - n]


def _seg_cummax(x, start):
    """Running max of x restarting where start is True."""

    def op(a, b):
        fa, xa = a
        fb, xb = b
        return fa | fb, jnp.where(fb, xb, jnp.maximum(xa, xb))

    return jax.lax.associative_scan(op, (start, x))[1]


def _seg_rev(x, last, fn):
    """Reverse running fn (jnp.minimum / jnp.maximum) of x restarting where last is True."""

    def op(a, b):
        fa, xa = a
        fb, xb = b
        return fa | fb, jnp.where(fb, xb, fn(xa, xb))

    return jax.lax.associative_scan(op, (last[::-1], x[::-1]))[1][::-1]


def _seg_cumsum(x, pid, bnd):
    """Cumulative sum of x (T,) restarting at every piece start (inclusive)."""
    K = bnd.shape[0] - 1
    T = x.shape[0]
    C = jnp.concatenate([jnp.zeros((1,), x.dtype), jnp.cumsum(x)])
    return C[1:] - C[jnp.clip(bnd[:K], 0, T)][pid]


class _Funnel(NamedTuple):
    """I2b's funnel per step (T,): delta the increment gap of B+ over B-, first / last step of
    each piece, [lo, hi] the X values from which the piece's end can still be reached; and
    feasible (K,): every piece has a sequence within the limits."""

    delta: jax.Array
    first: jax.Array
    lo: jax.Array
    hi: jax.Array
    feasible: jax.Array


def _funnel(dE_plus, dE_minus, pid, bnd, E_start, E_end, E_min, E_max, tol_pin, tol_v):
    """The parallel part of `_switching` (segmented scans): its `_Funnel`."""
    K = bnd.shape[0] - 1
    T = dE_plus.shape[0]
    k = jnp.arange(T)
    delta = jnp.maximum(dE_plus - dE_minus, 0.0)
    Ck = _seg_cumsum(delta, pid, bnd)  # C after step k (piece-local)
    base = E_start[pid] + _seg_cumsum(dE_minus, pid, bnd)  # E_b after step k on B-
    first = k == bnd[pid]
    last = (k + 1) == bnd[pid + 1]
    L = jnp.where(last, E_end[pid] - tol_pin, E_min - tol_v) - base
    U = jnp.where(last, E_end[pid] + tol_pin, E_max + tol_v) - base
    hi = _seg_rev(U, last, jnp.minimum)
    lo = _seg_rev(L - Ck, last, jnp.maximum) + Ck
    bad = (lo > hi) | (first & ((lo - delta > 0.0) | (hi < 0.0)))
    feasible = ~(jax.ops.segment_max(bad.astype(jnp.int32), pid, num_segments=K) > 0)
    return _Funnel(delta=delta, first=first, lo=lo, hi=hi, feasible=feasible)


def _switching(dE_plus, dE_minus, pid, bnd, E_start, E_end, E_min, E_max, tol_pin, tol_v):
    """Segmented I2b: the fewest switches per piece; see `minimal_switching`.

    Returns (sel (T,), n_switches (K,), feasible (K,)). Per piece, X(k) = E_b(k) - E_start -
    sum dE_minus (piece-local) is non-decreasing with increments in [0, delta_k]; the funnel
    [lo, hi] of X values from which the piece's end value can still be reached is computed by
    segmented reverse scans (`_funnel`), then a greedy forward pass keeps the current
    trajectory as long as the funnel allows (`_greedy`, a sequential scan).
    """
    f = _funnel(dE_plus, dE_minus, pid, bnd, E_start, E_end, E_min, E_max, tol_pin, tol_v)
    sel, n = _greedy(f, pid, bnd.shape[0] - 1)
    return sel, n, f.feasible


def _greedy(f: _Funnel, pid, K):
    """I2b's greedy forward pass through the funnel, from either trajectory: (sel (T,),
    n_switches (K,)) of the start with fewer switches (ties: B-)."""
    delta, first, lo, hi = f.delta, f.first, f.lo, f.hi
    k = jnp.arange(delta.shape[0])

    def run(p0):
        def step(c, i):
            X, p = c
            X = jnp.where(first[i], 0.0, X)
            p = jnp.where(first[i], p0, p)
            d = delta[i]
            ds = jnp.where(d > 0, d, 1.0)
            s_up = jnp.clip((hi[i] - X) / ds, 0.0, 1.0)  # on B+: stop at hi
            s_dn = jnp.clip((lo[i] - X) / ds, 0.0, 1.0)  # on B-: leave when lo catches up
            s = jnp.where(d > 0, jnp.where(p == 1, s_up, s_dn), p.astype(d.dtype))
            p_new = jnp.where(
                d > 0,
                jnp.where(p == 1, (s_up >= 1.0).astype(p.dtype), (s_dn > 0.0).astype(p.dtype)),
                p,
            )
            return (X + s * d, p_new), (s, p_new != p)

        _, (sel, sw) = jax.lax.scan(step, (jnp.zeros((), delta.dtype), p0), k)
        return sel, jax.ops.segment_sum(sw.astype(jnp.int32), pid, num_segments=K)

    sel0, n0 = run(jnp.int32(0))
    sel1, n1 = run(jnp.int32(1))
    use1 = n1 < n0
    return jnp.where(use1[pid], sel1, sel0), jnp.where(use1, n1, n0)


def _piece_paths(dE, pid, bnd, E_start, sat, E_max):
    """E_b over the horizon, each piece restarted at its start value.

    Returns (E, S, excess), each (T+1,): E the path (reflected at E_max in pieces with sat), S
    the free path, excess the energy dumped so far in the piece. E[0] = E_start[0]; E[j]
    (j >= 1) lies at the end of step j-1, in piece pid[j-1].
    """
    K = bnd.shape[0] - 1
    T = dE.shape[0]
    C = jnp.concatenate([jnp.zeros((1,), dE.dtype), jnp.cumsum(dE)])
    C_start = C[jnp.clip(bnd[:K], 0, T)]
    S = E_start[pid] + C[1:] - C_start[pid]  # (T,) free path at the end of each step
    start = jnp.concatenate([jnp.ones((1,), bool), pid[1:] != pid[:-1]])
    excess = jnp.where(sat[pid], jnp.maximum(_seg_cummax(S - E_max, start), 0.0), 0.0)
    head = E_start[:1]
    zero = jnp.zeros((1,), dE.dtype)
    return (jnp.concatenate([head, S - excess]), jnp.concatenate([head, S]),
            jnp.concatenate([zero, excess]))


def _piece_ends(dE, pid, bnd, E_start, sat, E_max):
    """End value of every piece (K,): free, or reflected at E_max where sat."""
    K = bnd.shape[0] - 1
    T = dE.shape[0]
    C = jnp.concatenate([jnp.zeros((1,), dE.dtype), jnp.cumsum(dE)])
    C_start = C[jnp.clip(bnd[:K], 0, T)]
    end_free = E_start + C[jnp.clip(bnd[1:], 0, T)] - C_start  # `piece_sums`, by bnd

    def reflected():  # the peak of each piece's free path, only where a piece is saturated
        S = E_start[pid] + C[1:] - C_start[pid]
        peak = jax.ops.segment_max(S - E_max, pid, num_segments=K)  # -inf on empty pieces
        return jnp.where(sat, end_free - jnp.maximum(peak, 0.0), end_free)

    return jax.lax.cond(jnp.any(sat), reflected, lambda: end_free)


class _Pieces(NamedTuple):
    lo: jax.Array  # (K,)
    hi: jax.Array  # (K,)
    r_plus: jax.Array  # (K,) I2a fraction on the B+ (lo) trajectory
    sat: jax.Array  # (K,) bool
    jump: jax.Array  # (K,) bool: end values at lo and hi differ by more than tol
    dE_plus: jax.Array  # (T,)
    dE_minus: jax.Array  # (T,)
    Ef_plus: jax.Array  # (T,)
    Ef_minus: jax.Array  # (T,)
    E: jax.Array  # (T+1,) mixed piecewise path
    pid: jax.Array  # (T,)
    miss: jax.Array  # (K,) bool: a used piece whose path misses its end value by > tol
    over: jax.Array  # (T+1,) upper violation measure (see _solve_pieces)
    under: jax.Array  # (T+1,) lower violation measure
    sw_ok: jax.Array  # (K,) bool: an I2b sequence within the limits exists (`_funnel`)


def bracket_held(ends, up, lo, hi, lam_lo, lam_hi, end_values, rounds: int = 8):
    """A bisection's bracket [lo, hi] whose ends, evaluated again, are on the sides the
    bisection left them: up(lo) and not up(hi), wherever it moved them from [lam_lo, lam_hi].

    ends(lo, hi) -> out, the evaluation at the ends; end_values(out) -> (e_lo, e_hi), what up
    (-> bool, per piece) decides on. Where an end evaluates on the wrong side (a tie that rounds
    otherwise here than in the bisection's loop), it moves outward by 16 ulps of the costate,
    then 4 times more each round, at most `rounds` rounds, never beyond lam_lo / lam_hi. Where
    every end holds (nearly always) the loop does not run and (lo, hi, out) are the first
    evaluation's. Returns (lo, hi, out)."""
    dtype = lo.dtype
    ulp = jnp.finfo(dtype).eps * jnp.maximum(jnp.maximum(jnp.abs(lo), jnp.abs(hi)), 1.0)

    def broken(lo, hi, out):
        e_lo, e_hi = end_values(out)
        return (lo > lam_lo) & ~up(e_lo), (hi < lam_hi) & up(e_hi)

    def cond(c):
        lo, hi, out, n = c
        b_lo, b_hi = broken(lo, hi, out)
        return (n < rounds) & jnp.any(b_lo | b_hi)

    def body(c):
        lo, hi, out, n = c
        b_lo, b_hi = broken(lo, hi, out)
        step = 16.0 * ulp * (4.0 ** n.astype(dtype))
        lo = jnp.where(b_lo, jnp.maximum(lo - step, lam_lo), lo)
        hi = jnp.where(b_hi, jnp.minimum(hi + step, lam_hi), hi)
        return lo, hi, ends(lo, hi), n + 1

    lo, hi, out, _ = jax.lax.while_loop(cond, body, (lo, hi, ends(lo, hi), jnp.int32(0)))
    return lo, hi, out


def _solve_pieces(vp, tab, ok, dt, bnd, E_bnd, E_min, E_max, lam_lo, lam_hi, tol, n_iter):
    """Bisect every piece at once; mix the bracketing trajectories (I2a)."""
    K = bnd.shape[0] - 1
    T = ok.shape[0]
    pid = piece_ids(bnd, T)
    E_start, tgt = E_bnd[:K], E_bnd[1:]
    lo = jnp.full((K,), lam_lo, dtype=E_bnd.dtype)
    hi = jnp.full((K,), lam_hi, dtype=E_bnd.dtype)
    run = partial(table_pass, vp, tab, ok)
    tol_v = _tol_v(tol, E_bnd.dtype)
    # the free path crosses E_max even at the most discharging lambda: the overshoot cannot be
    # avoided (recuperation beyond the battery), so the piece is reflected at E_max
    free = jnp.zeros((K,), bool)
    dE_cheap = run(hi[pid], dt)[0]  # the most discharging lambda: charging there is free
    _, S_hi, _ = _piece_paths(dE_cheap, pid, bnd, E_start, free, E_max)
    sat = jax.ops.segment_max(S_hi[1:] - E_max, pid, num_segments=K) > tol_v

    def cond(c):  # stop once no bracket can shrink (float32: after about 28 halvings)
        i, lo, hi = c[:3]
        mid = 0.5 * (lo + hi)
        return (i < n_iter) & jnp.any((mid > lo) & (mid < hi))

    def body(c):
        i, lo, hi = c
        mid = 0.5 * (lo + hi)
        end = _piece_ends(run(mid[pid], dt)[0], pid, bnd, E_start, sat, E_max)
        # too much left: raise lam (saturated pieces: the largest lam that still ends on target)
        up = jnp.where(sat, end >= tgt - tol_v, end > tgt)
        return i + 1, jnp.where(up, mid, lo), jnp.where(up, hi, mid)

    # n_iter halvings, fewer where the bracket already is one ulp wide: the halving is then
    # idempotent (mid rounds to lo, where the end stays above target, or to hi), so stopping
    # changes nothing. The loop carries the brackets alone, and the trajectories at their ends
    # are passed after it: carried too, XLA fused the pass into each of their four selects
    # and ran it four times per halving (3x slower under the elemental emitters)
    _, lo, hi = jax.lax.while_loop(cond, body, (jnp.int32(0), lo, hi))

    def ends(lo, hi):  # the trajectories at the bracket's ends and their pieces' end values
        dE_lo, Ef_lo = run(lo[pid], dt)
        dE_hi, Ef_hi = run(hi[pid], dt)
        return (dE_lo, Ef_lo, dE_hi, Ef_hi, _piece_ends(dE_lo, pid, bnd, E_start, sat, E_max),
                _piece_ends(dE_hi, pid, bnd, E_start, sat, E_max))

    # The loop leaves every end it moved on its side: too much left at lo (up), not at hi.
    # Evaluated again here, in another part of the program, an end within an ulp of a guard can
    # come out on the other side: at a guard's exact ties XLA may round H = P_f - lam P_bi with
    # or without a fused multiply-add, and where the route's steps share one guard (a cruise)
    # they all flip at once (Long Haul in float32, vmapped over 2 host devices: the piece then
    # missed its end value by 1.9 MJ, its violations were not counted, and Level 2 returned one
    # piece without the battery's limits). Such an end moves outward, by a step that grows from
    # 16 ulps, until it holds; elsewhere nothing changes (`bracket_held`).
    lo, hi, (dE_lo, Ef_lo, dE_hi, Ef_hi, end_p, end_m) = bracket_held(
        ends, lambda e: jnp.where(sat, e >= tgt - tol_v, e > tgt), lo, hi, lam_lo, lam_hi,
        lambda out: out[4:])
    den = end_p - end_m
    r_plus = jnp.clip(jnp.where(den > 0, (tgt - end_m) / jnp.where(den > 0, den, 1.0), 0.5), 0, 1)

    # eq. 55 is linear in r for free pieces; a reflected end is not, so bisect r there
    def rbody(_, c):
        ra, rb = c
        rm = 0.5 * (ra + rb)
        e = _piece_ends(rm[pid] * dE_lo + (1 - rm[pid]) * dE_hi, pid, bnd, E_start, sat, E_max)
        low = e < tgt
        return jnp.where(low, rm, ra), jnp.where(low, rb, rm)

    def r_reflected():
        ra, rb = jax.lax.fori_loop(0, 30, rbody, (jnp.zeros_like(lo), jnp.ones_like(lo)))
        return jnp.where(sat & (den > 0), 0.5 * (ra + rb), r_plus)

    r_plus = jax.lax.cond(jnp.any(sat), r_reflected, lambda: r_plus)
    sel = r_plus[pid]
    dE_mix = sel * dE_lo + (1 - sel) * dE_hi
    E, _, excess = _piece_paths(dE_mix, pid, bnd, E_start, sat, E_max)
    miss = (jnp.abs(E[bnd[1:]] - tgt) > tol) & (bnd[1:] > bnd[:K])
    # upper violations: E - E_max in free pieces. In a saturated piece an arc on E_max takes
    # free charge (charging even at the most discharging lambda: recuperation, dumped whatever
    # lambda_b); where the arc holds E_max without it, before, between or after free charge,
    # the battery could have driven (refilled for free by that charge) or the engine charges
    # it in vain. I1 splits at the end of a run of free charge, measured by the energy held
    # back so on the arc between that run and the arc's next free charge (or its end), for the
    # arc's first run also before it (what the most discharging lambda would draw there, and
    # the engine's charge dumped), for its last run also the energy dumped so far: so that
    # the free charge ends a piece, which then reaches E_max no earlier than it must, and what
    # follows gets its own costate. An arc without free charge splits at its exit (measured by
    # the energy dumped so far in the piece).
    j = jnp.arange(T + 1)
    big = jnp.int32(T + 2)
    p_prev = pid[jnp.clip(j - 1, 0, T - 1)]
    p_next = pid[jnp.clip(j, 0, T - 1)]
    E_next = E[jnp.clip(j + 1, 0, T)]
    on = E >= E_max - tol_v
    exit_ = (j >= 1) & (j < T) & (p_prev == p_next) & on & (E_next < E_max - tol_v)
    free_in = on & (j >= 1) & (dE_cheap[jnp.clip(j - 1, 0, T - 1)] > 0)  # step j-1 free
    same_next = (j < T) & jnp.roll(on, -1) & (p_next == p_prev)  # the arc goes on to j+1
    arc_end = ~(on & same_next)  # the last E index of its arc (or one off the arcs)
    arc = jnp.cumsum(jnp.concatenate([jnp.ones((1,), bool), arc_end[:-1]])) - 1
    prev_same = (j >= 2) & (p_prev == jnp.roll(p_prev, 1))
    dumped = excess - jnp.where(prev_same, jnp.roll(excess, 1), 0.0)  # in step j-1
    kept = jnp.maximum(-dE_cheap[jnp.clip(j - 1, 0, T - 1)], 0.0) + dumped
    D = jnp.cumsum(jnp.where(on & ~free_in & (j >= 1), kept, 0.0))  # held back, to j
    Dx = jnp.concatenate([jnp.zeros((1,), D.dtype), D])  # Dx[k]: held back to k - 1
    after = jax.ops.segment_max(j, arc, num_segments=T + 1)[arc] + 1  # past the arc's last
    nxt = jax.lax.cummin(jnp.where(free_in, j, big), reverse=True)  # the next free >= j
    nxt = jnp.where(same_next, nxt[jnp.clip(j + 1, 0, T)], big)  # ... > j
    nxt = jnp.where(nxt < after, nxt, big)  # ... in the arc
    gap = Dx[jnp.minimum(nxt, after)] - D  # held back after j, to the next free or the end
    first = jax.ops.segment_min(jnp.where(free_in, j, big), arc, num_segments=T + 1)[arc]
    arc_first = jax.ops.segment_min(j, arc, num_segments=T + 1)[arc]
    lead = Dx[jnp.minimum(first, T + 1)] - Dx[arc_first]  # held back before the first free
    F = jnp.cumsum(free_in)
    in_first = F - F[jnp.clip(first, 0, T)] == j - first  # j in the arc's first free run
    run_end = free_in & ~(same_next & jnp.roll(free_in, -1))
    held = gap + jnp.where(in_first, lead, 0.0) + jnp.where(nxt > T, excess, 0.0)
    over_sat = jnp.where(run_end, jnp.where(held > 0, held, -jnp.inf),
                         jnp.where(exit_ & (first > T), excess, -jnp.inf))
    over = jnp.where(sat[p_prev] & (j >= 1), over_sat, E - E_max)
    under = E_min - E
    # I2b: in free pieces a switching sequence between B+ and B- that stays within the limits
    # makes the piece solved, even where the constant I2a mix crosses a limit
    # (its sequence itself, a sequential scan, only for the final pieces: `_i2b_selection`)
    sw_ok = _funnel(dE_lo, dE_hi, pid, bnd, E_start, tgt, E_min, E_max, tol_v, tol_v).feasible
    fine = (~sat & sw_ok)[p_prev] & (j >= 1)
    over = jnp.where(fine, -jnp.inf, over)
    under = jnp.where(fine, -jnp.inf, under)
    return _Pieces(
        lo=lo, hi=hi, r_plus=r_plus, sat=sat, jump=den > tol, dE_plus=dE_lo, dE_minus=dE_hi,
        Ef_plus=Ef_lo, Ef_minus=Ef_hi, E=E, pid=pid, miss=miss, over=over, under=under,
        sw_ok=sw_ok,
    )


def _i2b_selection(sol: _Pieces, bnd, E_bnd, E_min, E_max, tol_v):
    """The selector of the solved pieces: I2b's sequence in free pieces that have one, else the
    I2a ratio. Returns (sel (T,), E_sel (T+1,) the path along sel, n_switches (K,))."""
    K = bnd.shape[0] - 1
    E_start, tgt = E_bnd[:K], E_bnd[1:]
    sel_sw, n_sw, _ = _switching(sol.dE_plus, sol.dE_minus, sol.pid, bnd, E_start, tgt, E_min,
                                 E_max, tol_v, tol_v)
    use = ~sol.sat & sol.sw_ok
    sel = jnp.where(use[sol.pid], sel_sw, sol.r_plus[sol.pid])
    dE_sel = sel * sol.dE_plus + (1 - sel) * sol.dE_minus
    E_sel, _, _ = _piece_paths(dE_sel, sol.pid, bnd, E_start, sol.sat, E_max)
    return sel, E_sel, jnp.where(use, n_sw, 0)


# ------------------------------------------------------------------------------ public result
class CostateResult(NamedTuple):
    """Level 2 solution for one vehicle and one route (K = max_pieces).

    lam: (T,) piecewise-constant costate lambda_b; lam0: () its first value (what Level 1 uses
    at t_0); E_b: (T+1,) battery energy (J), E_b[0] = E_b0, along `sel`: in pieces at a guard
    the I2b switching sequence (within the limits), in saturated pieces the I2a mix;
    E_b_i2a: (T+1,) the I2a path (constant mix per piece, eq. 55); n_switches: () switches of
    the I2b sequences; status: () int
    bit flags (OK = 0, see `status_names`); n_pieces: () number of pieces; boundaries: (K+1,)
    step indices of the piece boundaries, padded with T; E_bnd: (K+1,) E_b at the boundaries;
    lam_pieces, lam_lo, lam_hi, r_plus: (K,) per piece the costate, its final bisection bracket
    and the I2a fraction spent on the B+ (lam_lo) trajectory; saturated: (K,) bool;
    sel: (T,) selector (fraction of each step on B+; I2b, see E_b); dE_plus, dE_minus: (T,)
    E_b increments (J) of the B+ / B- trajectories; E_f_plus, E_f_minus: (T,) their fuel per
    step (J); fuel: () fuel energy (J) along sel;
    E_f: (T,) fuel energy per step (J); gear: (T,) gear index per step (0-based);
    max_violation: () largest excursion (J) of E_b beyond [E_min, E_max].
    """

    lam: jax.Array
    lam0: jax.Array
    E_b: jax.Array
    E_b_i2a: jax.Array
    n_switches: jax.Array
    status: jax.Array
    n_pieces: jax.Array
    boundaries: jax.Array
    E_bnd: jax.Array
    lam_pieces: jax.Array
    lam_lo: jax.Array
    lam_hi: jax.Array
    r_plus: jax.Array
    saturated: jax.Array
    sel: jax.Array
    dE_plus: jax.Array
    dE_minus: jax.Array
    E_f_plus: jax.Array
    E_f_minus: jax.Array
    fuel: jax.Array
    E_f: jax.Array
    gear: jax.Array
    max_violation: jax.Array


def _violations(sol: _Pieces, bnd):
    """(T+1,) violation of [E_min, E_max] at each E index (>= 0): zero at the boundaries and
    in pieces that miss their end value (splitting cannot repair them)."""
    j = jnp.arange(sol.over.shape[0])
    is_bnd = jnp.any(j[:, None] == bnd[None, :], axis=1)
    skip = jnp.concatenate([jnp.zeros((1,), bool), sol.miss[sol.pid]])
    viol = jnp.maximum(jnp.maximum(sol.over, sol.under), 0.0)
    return jnp.where(is_bnd | skip, 0.0, viol)


def _solve_core(
    vp, P_d, v, w, mask, dt, E_b0, E_b_end, E_min, E_max, lam_lo, lam_hi, tol_rel, *, n_iter,
    max_pieces, gears=None,
) -> CostateResult:
    K = max_pieces
    T = P_d.shape[0]
    dtype = jnp.result_type(P_d, float)
    gear, ok, tab = step_model(vp, P_d, v, w, mask, gears)
    tol = tol_rel * vp.E_b_max
    tol_v = _tol_v(tol, dtype)  # a violation smaller than this is rounding
    bnd = jnp.concatenate([jnp.zeros((1,), jnp.int32), jnp.full((K,), T, jnp.int32)])
    E_bnd = jnp.concatenate([jnp.full((1,), E_b0, dtype), jnp.full((K,), E_b_end, dtype)])
    solve = partial(
        _solve_pieces, vp, tab, ok, dt, E_min=E_min, E_max=E_max, lam_lo=lam_lo, lam_hi=lam_hi,
        tol=tol, n_iter=n_iter,
    )

    def n_used(bnd):
        return jnp.sum(bnd[1:] > bnd[:-1]).astype(jnp.int32)

    def refine(bnd, E_bnd, sol):
        """Split (or move) every piece at its own largest violation, largest first while
        pieces remain. Pieces are independent between boundaries, so this reaches what one
        split per round (the largest violation overall) reaches, in fewer rounds."""
        j = jnp.arange(T + 1)
        q = sol.pid[jnp.clip(j - 1, 0, T - 1)]  # the piece holding E index j (its end at j)
        viol = _violations(sol, bnd)
        vq = jax.ops.segment_max(viol, q, num_segments=K)  # (K,) largest per piece
        at_max = (viol == vq[q]) & (viol > 0)
        tc = jax.ops.segment_min(jnp.where(at_max, j, T + 1), q, num_segments=K)
        has = (vq > tol_v) & (tc <= T)
        tcc = jnp.clip(tc, 0, T)
        upper = sol.over[tcc] > sol.under[tcc]
        lim = jnp.where(upper, E_max, E_min).astype(dtype)
        # whether the violated stretch reaches back to the piece's start on a boundary at the
        # same limit: the constraint arc goes on, so that boundary moves forward to tc instead
        # of a new piece being added (forward only: no cycles)
        big = jnp.int32(T + 2)
        off_up = jax.ops.segment_min(jnp.where((j > 0) & ~(sol.E > E_max + tol_v), j, big), q,
                                     num_segments=K)
        off_dn = jax.ops.segment_min(jnp.where((j > 0) & ~(sol.E < E_min - tol_v), j, big), q,
                                     num_segments=K)
        back = jnp.where(upper, off_up, off_dn) > tc
        p = jnp.arange(K)
        mv = has & ~sol.sat & (p > 0) & (E_bnd[:K] == lim) & back & (tc < bnd[1:])
        split = has & ~mv
        # the largest violations first while pieces remain
        vr, vc = vq[None, :], vq[:, None]
        beats = (vr > vc) | ((vr == vc) & (p[None, :] < p[:, None]))
        rank = jnp.sum(split[None, :] & beats, axis=1)
        split = split & (rank < K - n_used(bnd))
        moved = jnp.concatenate([jnp.where(mv, tc, bnd[:K]), bnd[K:]]).astype(bnd.dtype)
        b2 = jnp.concatenate([moved, jnp.where(split, tc, T).astype(bnd.dtype)])
        e2 = jnp.concatenate([E_bnd, jnp.where(split, lim, E_bnd[K])])
        order = jnp.argsort(b2, stable=True)
        return b2[order][: K + 1], e2[order][: K + 1]

    # one traced solve: each round solves the current pieces, then refines them unless done
    def cond(c):
        return ~c[3]

    def body(c):
        bnd, E_bnd, _, _, i = c
        sol = solve(bnd, E_bnd)
        vmax = jnp.max(_violations(sol, bnd))
        done = ~((vmax > tol_v) & (n_used(bnd) < K) & (i < 3 * K))
        nb, ne = refine(bnd, E_bnd, sol)
        bnd = jnp.where(done, bnd, nb)
        E_bnd = jnp.where(done, E_bnd, ne)
        return bnd, E_bnd, sol, done, i + 1

    sol_shape = jax.eval_shape(lambda: solve(bnd, E_bnd))
    sol0 = jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype), sol_shape)
    # the last round leaves bnd unchanged, so sol is the solution of the final pieces
    bnd, E_bnd, sol, _, _ = jax.lax.while_loop(
        cond, body, (bnd, E_bnd, sol0, jnp.bool_(False), jnp.int32(0))
    )

    vmax = jnp.max(_violations(sol, bnd))
    miss = sol.miss
    used = bnd[1:] > bnd[:-1]
    status = jnp.int32(OK)
    status |= jnp.where(jnp.any(miss & used), INFEASIBLE, 0)
    status |= jnp.where(jnp.any(sol.jump & used), AT_GUARD, 0)
    status |= jnp.where(vmax > tol_v, PIECES_EXHAUSTED, 0)
    status |= jnp.where(jnp.any(sol.sat & used), SATURATED, 0)
    status |= jnp.where(jnp.any(mask & ~ok), STEP_INFEASIBLE, 0)
    lam_p = 0.5 * (sol.lo + sol.hi)
    lam = lam_p[sol.pid]
    sel, E_sel, n_sw = _i2b_selection(sol, bnd, E_bnd, E_min, E_max, tol_v)
    E_f = sel * sol.Ef_plus + (1 - sel) * sol.Ef_minus
    return CostateResult(
        lam=lam, lam0=lam[0], E_b=E_sel, E_b_i2a=sol.E, n_switches=jnp.sum(n_sw),
        status=status, n_pieces=n_used(bnd), boundaries=bnd,
        E_bnd=E_bnd, lam_pieces=lam_p, lam_lo=sol.lo, lam_hi=sol.hi, r_plus=sol.r_plus,
        saturated=sol.sat & used, sel=sel, dE_plus=sol.dE_plus, dE_minus=sol.dE_minus,
        E_f_plus=sol.Ef_plus, E_f_minus=sol.Ef_minus, fuel=jnp.sum(E_f), E_f=E_f, gear=gear,
        max_violation=vmax,
    )


SUM_BLOCK = 16  # the kernels run on a multiple of this many steps (`aligned_steps`)


def aligned_steps(T: int) -> int:
    """The number of steps the Level 2 kernels solve on for T steps: T rounded up to a multiple
    of `SUM_BLOCK`, the steps beyond T masked (a masked step moves no energy, so the solution is
    the same). XLA's CPU backend computes a cumulative sum (each pass's battery path) in blocks
    of 16 and pads the last block; fused with the pass that produces the sum's input, that
    padding made the whole pass run as scalar code: one pass and its path over 1000 steps took
    22 us, over 1008 steps 10 (float32, one core; the MPC's 1000-step windows ran twice as
    fast aligned). Routes' step counts are bucketed (`velocity.steps_for`) and need nothing."""
    return -(-T // SUM_BLOCK) * SUM_BLOCK


def _aligned(P_d, v, w, mask, gears):
    """The kernels' step inputs padded to `aligned_steps` with masked steps (ok False in
    `gears`: a (gear, ok) pair or a `StepModel`, if given)."""
    T = jnp.shape(P_d)[0]
    k = aligned_steps(T) - T
    if k == 0:
        return P_d, v, w, mask, gears

    def pad(a):
        a = jnp.asarray(a)
        return jnp.concatenate([a, jnp.zeros((k,) + a.shape[1:], a.dtype)])

    gears = None if gears is None else jax.tree.map(pad, gears)
    return pad(P_d), pad(v), pad(w), pad(mask), gears


def _defaults(vp, E_b0, E_b_end, E_max):
    """NaN means "default": E_b0 = soc0 E_b_max, E_b_end = E_b0, E_max = E_b_max."""
    E_b0 = jnp.where(jnp.isnan(E_b0), vp.soc0 * vp.E_b_max, E_b0)
    E_b_end = jnp.where(jnp.isnan(E_b_end), E_b0, E_b_end)
    E_max = jnp.where(jnp.isnan(E_max), vp.E_b_max, E_max)
    return E_b0, E_b_end, E_max


def costate_kernel(
    vp: VehicleParams, P_d, v, w, mask, dt, E_b0=jnp.nan, E_b_end=jnp.nan, E_min=0.0,
    E_max=jnp.nan, lam_min=LAM_BRACKET[0], lam_max=LAM_BRACKET[1], tol_rel=1e-3, *,
    n_iter: int = 40, max_pieces: int = 16, gears=None,
) -> CostateResult:
    """The unvalidated, traceable Level 2 kernel (one vehicle, one route); see `solve_costate`.

    P_d, v, w: (T,), mask: (T,) bool, every other argument a scalar (array leaves: new values
    never recompile). NaN E_b0 / E_b_end / E_max mean soc0 E_b_max / E_b0 / E_b_max.
    gears: `select_gears(vp, P_d, v, w, mask)`, or the `step_model` of the steps, if already
    at hand (a receding horizon slices the whole route's: both are step by step).
    It solves on `aligned_steps(T)` steps, the added ones masked, and returns the T steps'.
    """
    E_b0, E_b_end, E_max = _defaults(vp, E_b0, E_b_end, E_max)
    T = jnp.shape(P_d)[0]
    P_d, v, w, mask, gears = _aligned(P_d, v, w, mask, gears)
    res = _solve_core(
        vp, P_d, v, w, mask, dt, E_b0, E_b_end, E_min, E_max, lam_min, lam_max, tol_rel,
        n_iter=n_iter, max_pieces=max_pieces, gears=gears,
    )
    if res.lam.shape[0] == T:
        return res
    steps = {f: getattr(res, f)[:T] for f in ("lam", "sel", "dE_plus", "dE_minus", "E_f_plus",
                                               "E_f_minus", "E_f", "gear")}
    return res._replace(**steps, E_b=res.E_b[:T + 1], E_b_i2a=res.E_b_i2a[:T + 1],
                        boundaries=jnp.minimum(res.boundaries, T).astype(res.boundaries.dtype))


_costate_jit = jit(costate_kernel, static_argnames=("n_iter", "max_pieces"))


def _validate_route(P_d, v, w, mask, dt, batch: bool):
    P_d, v, w = (np.asarray(x, dtype=float) for x in (P_d, v, w))
    want = 2 if batch else 1
    if P_d.ndim != want or P_d.shape[-1] < 1:
        raise ValueError(f"P_d: expected shape {'(B, T)' if batch else '(T,)'}, got {P_d.shape}")
    for name, x in (("v", v), ("w", w)):
        if x.shape != P_d.shape:
            raise ValueError(f"{name}: shape {x.shape} differs from P_d {P_d.shape}")
        if not np.all(np.isfinite(x)):
            raise ValueError(f"{name}: contains non-finite values")
    if not np.all(np.isfinite(P_d)):
        raise ValueError("P_d: contains non-finite values")
    if np.any(v < 0) or np.any(w < 0):
        raise ValueError("v, w: speeds must be >= 0")
    mask = np.ones(P_d.shape, bool) if mask is None else np.asarray(mask, dtype=bool)
    if mask.shape != P_d.shape:
        raise ValueError(f"mask: shape {mask.shape} differs from P_d {P_d.shape}")
    dt = np.asarray(dt, dtype=float)
    if not (np.all(np.isfinite(dt)) and np.all(dt > 0)):
        raise ValueError(f"dt: must be a positive number of seconds (got {dt})")
    return P_d, v, w, mask, dt


def _validate_levels(vp, E_b0, E_b_end, E_min, E_max, lam_bracket, n_iter, max_pieces):
    check_vehicle(vp)
    lo, hi = (float(x) for x in lam_bracket)
    if not lo < hi:
        raise ValueError(f"lam_bracket: expected (low, high) with low < high, got {lam_bracket}")
    if int(n_iter) < 1 or int(max_pieces) < 1:
        raise ValueError("n_iter and max_pieces must be >= 1")
    e_max = np.asarray(vp.E_b_max if E_max is None else E_max, dtype=float)
    e0 = np.asarray(vp.soc0 * vp.E_b_max if E_b0 is None else E_b0, dtype=float)
    if np.any(np.asarray(E_min) >= e_max):
        raise ValueError(f"E_min ({E_min}) must be below E_max ({e_max})")
    for name, e in (("E_b0", e0), ("E_b_end", None if E_b_end is None else E_b_end)):
        if e is None:
            continue
        e = np.asarray(e, dtype=float)
        if not np.all(np.isfinite(e)) or np.any(e < np.asarray(E_min)) or np.any(e > e_max):
            raise ValueError(f"{name}: must lie within [E_min, E_max] = [{E_min}, {e_max}] J")
    nan = np.nan
    return (
        _f64(nan if E_b0 is None else E_b0), _f64(nan if E_b_end is None else E_b_end),
        _f64(E_min), _f64(nan if E_max is None else E_max), _f64(lo), _f64(hi),
    )


def _f64(x):
    """x as a float64 NumPy value: the one type the public functions pass their scalars to the
    kernels in (a Python float is weakly typed, and jit compiles once more for it than for a
    NumPy or JAX scalar of the same value)."""
    return np.asarray(x, dtype=float)


def solve_costate(
    vp: VehicleParams, P_d, v, w, mask=None, dt=1.0, E_b0=None, E_b_end=None, E_min=0.0,
    E_max=None, *, lam_bracket=LAM_BRACKET, tol_rel=1e-3, n_iter: int = 40,
    max_pieces: int = 16,
) -> CostateResult:
    """Level 2 for one vehicle and one route: the piecewise-constant costate lambda_b.

    P_d: (T,) mean driveline power (W); v: (T,) mean speed (m/s); w: (T,) gearbox input speed
    omega (rad/s) the gear is chosen from; mask: (T,) bool, False on padded steps (default all
    True); dt: step (s). E_b0: start energy (J, default soc0 E_b_max); E_b_end: end value (J,
    default E_b0: charge sustaining); battery limits [E_min, E_max] (J, default [0, E_b_max]).
    lam_bracket: the bisection bracket of lambda_b; tol_rel: tolerance on E_b(t_f) as a
    fraction of E_b_max (also the jump size that flags a guard); n_iter: bisection iterations;
    max_pieces: K, the most pieces I1 may use (1: plain bisection, limits only reported).

    Inputs are validated here (ValueError naming the argument); the kernel is jitted once per
    shape and static (n_iter, max_pieces). Returns `CostateResult` (status bit flags, no
    exceptions from inside jit).
    """
    P_d, v, w, mask, dt = _validate_route(P_d, v, w, mask, dt, batch=False)
    E_b0, E_b_end, E_min, E_max, lo, hi = _validate_levels(
        vp, E_b0, E_b_end, E_min, E_max, lam_bracket, n_iter, max_pieces
    )
    return _costate_jit(
        vp, P_d, v, w, mask, dt, E_b0, E_b_end, E_min, E_max, lo, hi, _f64(tol_rel),
        n_iter=int(n_iter), max_pieces=int(max_pieces),
    )


def bisect_costate(vp, P_d, v, w, mask=None, dt=1.0, E_b0=None, E_b_end=None, **kw):
    """Plain bisection on one constant lambda_b (no battery limits): E_b(t_f) = E_b_end.

    Same arguments as `solve_costate`; the limits are set to +-inf and max_pieces to 1.
    """
    e0 = vp.soc0 * vp.E_b_max if E_b0 is None else E_b0
    return solve_costate(
        vp, P_d, v, w, mask, dt, e0, E_b_end, -np.inf, np.inf, max_pieces=1, **kw
    )


@jit(static_argnames=("n_iter", "max_pieces"))
def _batch_jit(vp, P_d, v, w, mask, dt, E_b0, E_b_end, E_min, E_max, lo, hi, tol, *, n_iter,
               max_pieces):
    f = partial(costate_kernel, n_iter=n_iter, max_pieces=max_pieces)
    return jax.vmap(f)(vp, P_d, v, w, mask, dt, E_b0, E_b_end, E_min, E_max, lo, hi, tol)


@jit(static_argnames=("n_iter", "max_pieces"))
def _product_jit(vp, P_d, v, w, mask, dt, E_b0, E_b_end, E_min, E_max, lo, hi, tol, *, n_iter,
                 max_pieces):
    f = partial(costate_kernel, n_iter=n_iter, max_pieces=max_pieces)
    over_vehicles = jax.vmap(f, in_axes=(0,) + (None,) * 5 + (0,) * 7)
    over_routes = jax.vmap(over_vehicles, in_axes=(None,) + (0,) * 5 + (None,) * 7)
    return over_routes(vp, P_d, v, w, mask, dt, E_b0, E_b_end, E_min, E_max, lo, hi, tol)


def _per_vehicle(vp, n):
    """Broadcast every leaf of vp (batched or not) to a leading axis of n."""
    if np.ndim(vp.mass) == 0:
        return jax.tree.map(lambda x: np.broadcast_to(x, (n,) + np.shape(x)), vp)
    if np.shape(vp.mass)[0] != n:
        raise ValueError(f"vehicle batch of {np.shape(vp.mass)[0]} does not match {n}")
    return jax.tree.map(lambda x: np.broadcast_to(x, (n,) + np.shape(x)[1:]), vp)


def _opt(x, n):
    return np.broadcast_to(np.asarray(np.nan if x is None else x, dtype=float), (n,))


def costate_batch(
    vp: VehicleParams, P_d, v, w, mask=None, dt=1.0, E_b0=None, E_b_end=None, E_min=0.0,
    E_max=None, *, lam_bracket=LAM_BRACKET, tol_rel=1e-3, n_iter: int = 40,
    max_pieces: int = 16,
) -> CostateResult:
    """`solve_costate` over a batch of B (vehicle, route) pairs: one jitted vmap.

    P_d, v, w, mask: (B, T); vp: a vehicle (broadcast) or a stacked batch of B vehicles
    (`stack_vehicles`; battery sizes are the leaf E_b_max); dt, E_b0, E_b_end, E_min, E_max:
    scalars or (B,). Returns `CostateResult` with a leading axis B.
    """
    P_d, v, w, mask, dt = _validate_route(P_d, v, w, mask, dt, batch=True)
    B = P_d.shape[0]
    vpb = _per_vehicle(vp, B)
    _validate_levels(
        vpb, E_b0, E_b_end, E_min, E_max, lam_bracket, n_iter, max_pieces
    )
    lo, hi = (np.full((B,), float(x)) for x in lam_bracket)
    return _batch_jit(
        vpb, P_d, v, w, mask, np.broadcast_to(dt, (B,)), _opt(E_b0, B), _opt(E_b_end, B),
        _opt(E_min, B), _opt(E_max, B), lo, hi, np.full((B,), float(tol_rel)),
        n_iter=int(n_iter), max_pieces=int(max_pieces),
    )


def costate_product(
    vp: VehicleParams, P_d, v, w, mask=None, dt=1.0, *, E_min=0.0, lam_bracket=LAM_BRACKET,
    tol_rel=1e-3, n_iter: int = 40, max_pieces: int = 16,
) -> CostateResult:
    """Every route with every vehicle: results with leading axes (R routes, V vehicles).

    P_d, v, w, mask: (R, T); vp: a stacked batch of V vehicles (masses, battery sizes, ...);
    dt: scalar or (R,). Each vehicle starts at soc0 E_b_max and is charge sustaining.
    """
    P_d, v, w, mask, dt = _validate_route(P_d, v, w, mask, dt, batch=True)
    R = P_d.shape[0]
    if np.ndim(vp.mass) == 0:
        raise ValueError("costate_product: vp must be a stacked batch of vehicles")
    V = np.shape(vp.mass)[0]
    _validate_levels(vp, None, None, E_min, None, lam_bracket, n_iter, max_pieces)
    lo, hi = (np.full((V,), float(x)) for x in lam_bracket)
    nan = np.full((V,), np.nan)
    return _product_jit(
        vp, P_d, v, w, mask, np.broadcast_to(dt, (R,)), nan, nan,
        np.broadcast_to(float(E_min), (V,)), nan, lo, hi, np.full((V,), float(tol_rel)),
        n_iter=int(n_iter), max_pieces=int(max_pieces),
    )


# ------------------------------------------------------------------------- I2b minimal switching
class Switching(NamedTuple):
    """A switching sequence between the B+ and B- trajectories (I2b).

    sel: (T,) fraction of each step on B+ (0 or 1 except at the switching steps, where the
    switch falls inside the step); E_b: (T+1,) battery energy (J); n_switches: () int;
    feasible: () bool (a sequence within the limits and through the pinned values exists).
    """

    sel: jax.Array
    E_b: jax.Array
    n_switches: jax.Array
    feasible: jax.Array


@jit
def minimal_switching(dE_plus, dE_minus, E_b0, E_b_end, E_min, E_max, tol=1.0) -> Switching:
    """I2b (section 5.2.2, Figures 14-15): the fewest switches between two trajectories.

    dE_plus, dE_minus: (T,) E_b increments (J) of B+ and B- (dE_plus >= dE_minus step by step,
    which holds for the trajectories at the two sides of a guard); E_b0: start (J); E_b_end:
    end value (J); [E_min, E_max]: limits (J); tol: slack (J) on the limits and the end.

    With X(k) = E_b(k) - E_b0 - sum_{j<k} dE_minus_j, any selector s_k in [0, 1] gives a
    non-decreasing X with increments s_k (dE_plus_k - dE_minus_k). The limits and the end
    value bound X to a tube; the X values from which the end can still be reached form the
    funnel [lo_k, hi_k] (hi_k = min_{j>=k} U_j, lo_k = max_{j>=k} (L_j - C_j) + C_k, C the
    cumulative difference). Greedy forward pass: keep the current trajectory as long as the
    funnel allows and switch at the last moment, inside the step, so that the limit is just
    touched (the paper's advanced switching time, Figure 15). From the funnel's edge the other
    trajectory then runs longest, so the number of switches is minimal. Both starting
    trajectories are tried (ties: B-). The last switch is the paper's back-propagated one that
    puts E_b(t_f) on its end value.
    """
    T = dE_plus.shape[0]
    pid = jnp.zeros((T,), jnp.int32)
    bnd = jnp.array([0, T], jnp.int32)
    e0 = jnp.reshape(jnp.asarray(E_b0, dE_plus.dtype), (1,))
    e1 = jnp.reshape(jnp.asarray(E_b_end, dE_plus.dtype), (1,))
    sel, n, ok = _switching(dE_plus, dE_minus, pid, bnd, e0, e1, E_min, E_max, tol, tol)
    E = jnp.concatenate([e0, E_b0 + jnp.cumsum(sel * dE_plus + (1 - sel) * dE_minus)])
    return Switching(sel=sel, E_b=E, n_switches=n[0], feasible=ok[0])


# ------------------------------------------------------------------------ I3 limited horizon
class HorizonResult(NamedTuple):
    """Level 2 on a window that ends before the route does (I3).

    lam: () the costate for Level 1; E_b: (T+1,) predicted battery energy (J) over the window
    (I2a mix at a guard; under I3a the first sub-problem's trajectory, held after its end);
    margin: () smallest distance (J) of E_b to [E_min, E_max] (negative: a limit is crossed);
    status: () bit flags (AT_GUARD, I3A, I3B, INFEASIBLE, ...); r_plus: () I2a fraction on B+;
    lam_lo, lam_hi: () final bracket; t_event: () E index of the I3a event (T when none).
    """

    lam: jax.Array
    E_b: jax.Array
    margin: jax.Array
    status: jax.Array
    r_plus: jax.Array
    lam_lo: jax.Array
    lam_hi: jax.Array
    t_event: jax.Array


def horizon_kernel(
    vp: VehicleParams, P_d, v, w, mask, dt, E_b0, E_min=0.0, E_max=jnp.nan,
    lam_min=LAM_BRACKET[0], lam_max=LAM_BRACKET[1], tol_rel=1e-3, *, n_iter: int = 40,
    max_pieces: int = 4, gears=None,
) -> HorizonResult:
    """Traceable I3 kernel (one vehicle, one window); see `level2_horizon`. gears: as in
    `costate_kernel`; solved on `aligned_steps(T)` steps, as there."""
    T = jnp.shape(P_d)[0]
    P_d, v, w, mask, gears = _aligned(P_d, v, w, mask, gears)
    res = _horizon_core(vp, P_d, v, w, mask, dt, E_b0, E_min, E_max, lam_min, lam_max, tol_rel,
                        n_iter=n_iter, max_pieces=max_pieces, gears=gears)
    if res.E_b.shape[0] == T + 1:
        return res
    return res._replace(E_b=res.E_b[:T + 1], t_event=jnp.minimum(res.t_event, T))


def _horizon_core(vp, P_d, v, w, mask, dt, E_b0, E_min, E_max, lam_min, lam_max, tol_rel, *,
                  n_iter, max_pieces, gears):
    E_max = jnp.where(jnp.isnan(E_max), vp.E_b_max, E_max)
    T = P_d.shape[0]
    dtype = jnp.result_type(P_d, float)
    gear, ok, tab = step_model(vp, P_d, v, w, mask, gears)
    tol = tol_rel * vp.E_b_max

    def path(dE):
        return jnp.concatenate([jnp.reshape(E_b0, (1,)).astype(dtype), E_b0 + jnp.cumsum(dE)])

    def dists(E):
        return jnp.min(E - E_min), jnp.min(E_max - E)

    def run(lam):
        return table_pass(vp, tab, ok, lam, dt)[0]

    # g(lam) = d_low - d_up is non-increasing in lam: bisection on its sign maximises the
    # smaller distance min(d_low, d_up) (d_low falls and d_up rises with lam)
    def body(_, c):
        lo, hi = c
        mid = 0.5 * (lo + hi)
        a, b = dists(path(run(mid)))
        up = a > b
        return jnp.where(up, mid, lo), jnp.where(up, hi, mid)

    lo, hi = jax.lax.fori_loop(
        0, n_iter, body, (jnp.asarray(lam_min, dtype), jnp.asarray(lam_max, dtype)))

    def ends(lo, hi):  # after the loop, as in `_solve_pieces`
        E_plus, E_minus = path(run(lo)), path(run(hi))
        return E_plus, E_minus, dists(E_plus), dists(E_minus)

    # the ends on the sides the loop left them (`bracket_held`, as in `_solve_pieces`)
    lo, hi, (E_plus, E_minus, _, _) = bracket_held(ends, lambda d: d[0] > d[1], lo, hi, lam_min,
                                                   lam_max, lambda out: out[2:])

    # at a guard the two sides differ: mix them (I2a) to balance the two distances
    def rbody(_, c):
        a_, b_ = c
        r = 0.5 * (a_ + b_)
        x, y = dists(E_minus + r * (E_plus - E_minus))
        return jnp.where(x < y, r, a_), jnp.where(x < y, b_, r)

    ra, rb = jax.lax.fori_loop(0, 50, rbody, (jnp.zeros((), dtype), jnp.ones((), dtype)))
    r = 0.5 * (ra + rb)
    E_mix = E_minus + r * (E_plus - E_minus)
    a, b = dists(E_mix)
    margin = jnp.minimum(a, b)
    lam = 0.5 * (lo + hi)
    jump = jnp.max(E_plus - E_minus) > tol
    status = jnp.where(jump, AT_GUARD, OK)
    status |= jnp.where(jump & (E_plus[T] >= E_max - tol) & (E_minus[T] <= E_min + tol), I3B, 0)
    status |= jnp.where(jnp.any(mask & ~ok), STEP_INFEASIBLE, 0)

    # I3a: no lambda keeps E_b within the limits: the largest violation is an event the first
    # sub-problem must end on (its limit as end value)
    tol_v = _tol_v(tol, dtype)
    viol = jnp.maximum(jnp.maximum(E_mix - E_max, E_min - E_mix), 0.0)
    tc = jnp.argmax(viol).astype(jnp.int32)
    lim = jnp.where(E_mix[tc] > E_max, E_max, E_min)
    event = (margin < -tol_v) & (tc > 0)

    def first_subproblem(_):
        m = mask & (jnp.arange(T) < tc)
        res = _solve_core(vp, P_d, v, w, m, dt, E_b0, lim, E_min, E_max, lam_min, lam_max,
                          tol_rel, n_iter=n_iter, max_pieces=max_pieces,
                          gears=StepModel(gear, ok & m, tab))
        status = (res.status | I3A).astype(jnp.int32)
        return res.lam0, res.E_b, status, res.r_plus[0], res.lam_lo[0], res.lam_hi[0]

    def keep(_):
        return lam, E_mix, jnp.asarray(status, jnp.int32), r, lo, hi

    lam, E_out, status, r, lo, hi = jax.lax.cond(event, first_subproblem, keep, None)
    return HorizonResult(
        lam=lam, E_b=E_out, margin=margin, status=jnp.asarray(status, jnp.int32), r_plus=r,
        lam_lo=lo, lam_hi=hi, t_event=jnp.where(event, tc, T).astype(jnp.int32),
    )


_horizon_jit = jit(horizon_kernel, static_argnames=("n_iter", "max_pieces"))


def level2_horizon(
    vp: VehicleParams, P_d, v, w, mask=None, dt=1.0, E_b0=None, E_min=0.0, E_max=None, *,
    lam_bracket=LAM_BRACKET, tol_rel=1e-3, n_iter: int = 40, max_pieces: int = 4,
) -> HorizonResult:
    """I3 (section 5.3): lambda_b for a prediction window that ends before the route.

    P_d, v, w, mask: (T,) the window of the prediction (pad with mask = False to keep one
    shape in an MPC loop); E_b0: the current battery energy (J, default soc0 E_b_max).
    Without an end condition, lambda_b maximises the smallest distance of E_b to
    [E_min, E_max] over the window. I3a: if no lambda_b keeps E_b within the limits, the
    largest violation is an event (e.g. a long descent that fills the battery whatever
    lambda_b): the first sub-problem, from now to that event with the limit as end value, is
    solved (with I1 inside, up to max_pieces) and its first costate returned. I3b: on a guard
    whose two solutions span both limits at the window end, lambda_b is the guard value.
    """
    P_d, v, w, mask, dt = _validate_route(P_d, v, w, mask, dt, batch=False)
    _, _, E_min, E_max, lo, hi = _validate_levels(
        vp, E_b0, None, E_min, E_max, lam_bracket, n_iter, max_pieces
    )
    e0 = vp.soc0 * vp.E_b_max if E_b0 is None else E_b0
    return _horizon_jit(
        vp, P_d, v, w, mask, dt, _f64(e0), E_min, E_max, lo, hi, _f64(tol_rel),
        n_iter=int(n_iter), max_pieces=int(max_pieces),
    )
