"""Level 1 with switching costs: the mode x gear DP of eq. 45 (Figure 10), full horizon and MPC.

    min_{M, G}  sum_k  H*_1a(M, G, k) dt + eps_M(dM, k) + eps_G(dG, k)            (eq. 45)

The explicit Hamiltonian H*_1a of every mode and gear (`powersplit.hamiltonian_table`) is the
per-step state cost of a Viterbi recursion (`jaxems.dp`) over S = 4 x n_gears states
s = mode * n_gears + gear; the switching costs of Appendix C (`jaxems.switching`) are the
transition costs. The transition cost from step k-1 to step k uses the inputs of step k
(speed, grade, lambda_b) and, braking, what the switch loses of step k's recuperation
(`braking_loss`, added to the traction term). The state before step 0 is given
(``init_mode``, ``init_gear``) or free (``init_mode = -1``); the first step may already switch
away from it.

Steps where no (M, G) is feasible (a demand beyond the driveline's capability) get zero state
cost for every state, so the DP passes through them at the price of switching only; they are
counted in ``Level1Result.n_infeasible`` for the plant to deal with.

Structured relaxation. The transition cost is
    C_k((M, G) -> (M', G')) = -lambda_k (r_d v_k)^2 sum_c [u_c max(0, x'_c R'^2 - x_c R^2)
                              + d_c max(0, x_c R^2 - x'_c R'^2)] + t_k(kind, M', G')
(R = gear ratio, x_c = component c connected, u/d the weights of `switching.sync_weights`,
kind = mode-only / gear-only / both). With gear ratios decreasing in G (R(G) > R(G') for
G < G'), every max() resolves by the sign of G - G', so for a source mode M the minimum over
source gears splits into an exclusive prefix minimum (G < G'), the same gear, and an exclusive
suffix minimum (G > G') of V(M, G) + a W(G) terms: O(16 x n_gears) per step instead of
O(S^2). `relax_structured` implements it for any dt_M, dt_G. When dt_M == dt_G (the paper's
setting, and the reference truck) the traction cost depends on the target state only and the
synchronisation cost is scale_k * D with a constant per-vehicle matrix D; dividing V by scale_k
turns the relaxation into a min-plus product with that constant matrix
(`relax_same_open_time`), which vectorises best on CPU; it runs with the open mode's states,
which are equivalent, merged into one (`merge_open`: 37 states for 12 gears). `solve_dp` picks
it with `lax.cond` when every configuration has dt_M == dt_G. `switching.switch_cost_matrix`
is the dense reference both are tested against.

Batching: `level1_batch` solves routes x vehicles x lambda_b in one jitted call, running the DP
with the batch on the last axis (see `jaxems.dp`). Array values never recompile.
"""

from __future__ import annotations

import collections
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import dp
from .. import switching as sw
from ..params import VehicleParams, check_vehicle
from ..xla import jit
from .powersplit import (
    ENGINE_CONNECTED,
    MO,
    MOTOR_CONNECTED,
    N_MODES,
    hamiltonian_H,
    split_state,
)

TRACES: collections.Counter = collections.Counter()  # trace counts of the jitted entry points


class Level1Result(NamedTuple):
    """Level 1 decisions and powers along the route; shapes (T,) unless noted.

    mode: mode index (0 M_c, 1 M_e, 2 M_m, 3 M_o); gear: gear index (0 = gear 1); state:
    mode * n_gears + gear; P_b, P_e, P_m, P_f, P_brake (W), H (W), w (rad/s) of the chosen
    (mode, gear); switch_cost: J charged at step k for the switch into step k's state;
    cost: () J, sum of H dt + switch costs over unmasked steps (+inf if no feasible path);
    n_mode_switches, n_gear_switches: () int32; n_infeasible: () int32 steps without any
    feasible (mode, gear).
    """

    mode: jax.Array
    gear: jax.Array
    state: jax.Array
    P_b: jax.Array
    P_e: jax.Array
    P_m: jax.Array
    P_f: jax.Array
    P_brake: jax.Array
    H: jax.Array
    w: jax.Array
    switch_cost: jax.Array
    cost: jax.Array
    n_mode_switches: jax.Array
    n_gear_switches: jax.Array
    n_infeasible: jax.Array


class TransitionInputs(NamedTuple):
    """Per-step inputs of the Level 1 transition (leading axis T, then any batch axes).

    scale: -lambda_b (r_d v)^2 * weight (J per kg m^2 per unit ratio^2); trac: (3, S)
    traction costs (J) for mode-only / gear-only / both switches into each state.
    """

    scale: jax.Array
    trac: jax.Array


class TransitionConsts(NamedTuple):
    """Per-configuration constants of the structured relaxation (any trailing batch axes).

    W: (G,) squared gear ratios; a_lo: (4,), b_lo: (4, 4), a_hi: (4, 4), b_hi: (4,) the
    coefficients of W(G) and W(G') for G <= G' (lo) and G > G' (hi), indexed [M] / [M, M'].
    """

    W: jax.Array
    a_lo: jax.Array
    b_lo: jax.Array
    a_hi: jax.Array
    b_hi: jax.Array


# ------------------------------------------------------------------------------ transition
def transition_consts(vp: VehicleParams, averaged) -> TransitionConsts:
    """Coefficients of the structured relaxation for one vehicle (see the module docstring)."""
    u_e, d_e, u_m, d_m = sw.sync_weights(vp, averaged)
    dtype = jnp.result_type(u_e, float)
    xe = jnp.asarray(ENGINE_CONNECTED, dtype)
    xm = jnp.asarray(MOTOR_CONNECTED, dtype)

    def comp(x, u, d):
        x0, x1 = x[:, None], x[None, :]  # source M, target M'
        a_lo = x * d
        b_lo = x1 * (1 - x0) * u - x0 * x1 * d
        a_hi = x0 * (d * (1 - x1) - u * x1)
        b_hi = x * u
        return a_lo, b_lo, a_hi, b_hi

    e = comp(xe, u_e, d_e)
    m = comp(xm, u_m, d_m)
    a_lo, b_lo, a_hi, b_hi = (p + q for p, q in zip(e, m, strict=True))
    return TransitionConsts(W=vp.gear_ratio**2, a_lo=a_lo, b_lo=b_lo, a_hi=a_hi, b_hi=b_hi)


def transition_inputs(vp: VehicleParams, v, grade, lam, params: sw.SwitchCostParams,
                      trac=None):
    """`TransitionInputs` of one step (scalars v, grade, lam): scale () and trac (3, S).

    trac: the step's `traction_table` if already at hand (it does not depend on lam)."""
    scale = -lam * (vp.r_d * v) ** 2 * params.weight
    if trac is None:
        trac = sw.traction_cost_table(vp, v, grade, params) * params.weight
    return TransitionInputs(scale=scale, trac=trac)


def traction_table(vp: VehicleParams, v, grade, params: sw.SwitchCostParams):
    """(T, 3, S) J: the weighted traction-interruption costs of every step (v, grade: (T,)).
    They do not depend on lambda_b: a caller that solves Level 1 at many lambda_b on one
    prediction computes them once (`_tables`' ``trac``)."""
    f = jax.vmap(sw.traction_cost_table, in_axes=(None, 0, 0, None))
    return f(vp, v, grade, params) * params.weight


def _excl_scan(vals, reverse):
    """Exclusive running min (and argmin) along axis 1 of vals (A, G, *b), unrolled."""
    n_g = vals.shape[1]
    inf = jnp.full(vals[:, 0].shape, jnp.inf, vals.dtype)
    best, arg = inf, jnp.zeros(inf.shape, jnp.int8)
    outs_b, outs_a = [None] * n_g, [None] * n_g
    order = range(n_g - 1, -1, -1) if reverse else range(n_g)
    for g in order:
        outs_b[g], outs_a[g] = best, arg
        c = vals[:, g]
        better = c < best
        best = jnp.where(better, c, best)
        arg = jnp.where(better, jnp.int8(g), arg)
    return jnp.stack(outs_b, 1), jnp.stack(outs_a, 1)


def relax_structured(V, x: TransitionInputs, k: TransitionConsts):
    """best[s'] = min_s V[s] + C(s -> s') and its argmin for the Level 1 switching costs.

    V: (S, *b) with S = 4 * G; x: `TransitionInputs` of this step (scale (*b), trac (3, S, *b));
    k: `TransitionConsts` (W (G, *b), ...). Returns best, arg: (S, *b). Requires gear ratios
    decreasing in the gear index (validated by the Level 1 entry points).
    """
    S = V.shape[0]
    b = V.shape[1:]
    G = S // N_MODES
    nb = (1,) * len(b)
    Vm = V.reshape((N_MODES, G) + b)
    s = x.scale
    trac = x.trac.reshape((3, N_MODES, G) + b)
    W = k.W  # (G, *b)
    # exclusive prefix over source gears G < G' with a_lo(M):  (4, G, *b)
    A_lo = s * k.a_lo  # (4, *b)
    P, Pa = _excl_scan(Vm + A_lo[:, None] * W[None], reverse=False)
    # exclusive suffix over G > G' with a_hi(M, M'):  (4, 4, G, *b) -> flatten (16, G, *b)
    A_hi = s * k.a_hi  # (4, 4, *b)
    vals_hi = Vm[:, None] + A_hi[:, :, None] * W[None, None]
    Q, Qa = _excl_scan(vals_hi.reshape((16, G) + b), reverse=True)
    Q, Qa = Q.reshape((4, 4, G) + b), Qa.reshape((4, 4, G) + b)
    Wt = W[None, None]  # target gear G'
    lo = P[:, None] + (s * k.b_lo)[:, :, None] * Wt  # (4, 4, G, *b)
    hi = Q + (s * k.b_hi)[None, :, None] * Wt
    gear_change = jnp.minimum(lo, hi)
    g_arg = jnp.where(hi < lo, Qa, jnp.broadcast_to(Pa[:, None], Qa.shape))
    same = jnp.eye(N_MODES, dtype=bool).reshape((4, 4, 1) + nb)
    gear_change = gear_change + jnp.where(same, trac[1][None], trac[2][None])
    # same gear: stay (M == M', no cost) or a mode switch (trac row 0)
    eq = Vm[:, None] + (s * (k.a_lo[:, None] + k.b_lo))[:, :, None] * Wt + trac[0][None]
    eq = jnp.where(same, jnp.broadcast_to(Vm[None], eq.shape), eq)
    # eq wins ties (listed first) only if strictly better than the gear change
    use_eq = eq <= gear_change
    cand = jnp.where(use_eq, eq, gear_change)
    gidx = jnp.broadcast_to(jnp.arange(G, dtype=jnp.int8).reshape((1, 1, G) + nb), eq.shape)
    cand_g = jnp.where(use_eq, gidx, g_arg)
    # min over source modes M
    best, arg = cand[0], cand_g[0].astype(jnp.int16)
    for m in range(1, N_MODES):
        better = cand[m] < best
        best = jnp.where(better, cand[m], best)
        arg = jnp.where(better, (cand_g[m].astype(jnp.int16) + m * G), arg)
    return best.reshape((S,) + b), arg.reshape((S,) + b).astype(dp.pointer_dtype(S))


def structured_transition(xs: TransitionInputs, consts: TransitionConsts) -> dp.Transition:
    """The Level 1 switching costs as a `dp.Transition` (xs with leading axis T)."""
    return dp.Transition(relax=lambda V, x: relax_structured(V, x, consts), xs=xs)


# ------------------------------------------------------------ dense relaxation (dt_M == dt_G)
class DenseConsts(NamedTuple):
    """Per-configuration constant of `relax_same_open_time` (any trailing batch axes).

    D: (S, S) synchronisation energy per unit of (r_d v)^2 between all states (kg m^2 x
    ratio^2), so that the synchronisation cost of step k is scale_k * D.
    """

    D: jax.Array


def dense_consts(vp: VehicleParams, averaged) -> DenseConsts:
    """`DenseConsts` of one vehicle: the unit synchronisation matrix."""
    D = sw.sync_cost_matrix(vp._replace(r_d=jnp.ones_like(vp.r_d)), 1.0, -1.0, averaged)
    return DenseConsts(D=D)


def relax_same_open_time(V, x: TransitionInputs, k: DenseConsts):
    """Level 1 relaxation for the case dt_M == dt_G (one traction cost per target state).

    Then C(s -> s') = scale D(s, s') + t(s') for s != s' and 0 for s == s'. With scale > 0
    the minimum over sources is scale * min_s (V[s] / scale + D[s, s']): a min-plus product
    with the *constant* per-vehicle matrix D, the fastest dense form (no per-step matrix).
    scale == 0 (standstill or weight 0) falls back to min_s V[s]. V: (S, *b).
    """
    S = V.shape[0]
    b = V.shape[1:]
    pdt = dp.pointer_dtype(S)
    s = x.scale
    pos = s > 0
    s_safe = jnp.where(pos, s, 1.0)
    best, arg = dp.relax_dense(V / s_safe[None], k.D)
    vmin = jnp.min(V, axis=0)
    vam = jnp.argmin(V, axis=0).astype(pdt)
    best = jnp.where(pos[None], best * s_safe[None], vmin[None])
    arg = jnp.where(pos[None], arg, vam[None])
    best = best + x.trac[2]
    stay = V <= best
    ident = jnp.arange(S, dtype=pdt).reshape((S,) + (1,) * len(b))
    return jnp.where(stay, V, best), jnp.where(stay, ident, arg)


def fast_transition(xs: TransitionInputs, consts: DenseConsts) -> dp.Transition:
    """`relax_same_open_time` as a `dp.Transition` (valid when dt_M == dt_G)."""
    return dp.Transition(relax=lambda V, x: relax_same_open_time(V, x, consts), xs=xs)


def merge_open(stage, xs: TransitionInputs, dconsts: DenseConsts, init):
    """The DP's inputs with the open mode's n_gears states merged into one, (M_o, gear 1).

    Open, neither component is connected: the Hamiltonian (no traction; idling for a truck
    without a motor), the synchronisation energy into and out of the state (nothing turns)
    and the traction cost into it (none) do not depend on the gear held, and a gear change
    while open is no switch; the gear matters again only when a mode engages it, and that
    switch's cost depends on the target state alone. The open states are equivalent, so one
    stands for all: 3 n_gears + 1 states (37 for 12 gears, 0.59 of the relaxations), with the
    same optimum; among its equal-cost open states the full DP's path takes gear 1 as well
    (lowest index on ties) unless it starts open in another gear. Valid with
    `relax_same_open_time`, whose traction cost depends on the target state alone.
    stage: (T, S, *b), xs.trac: (T, 3, S, *b), dconsts.D: (S, S, *b), init: (S, *b) -> the
    same with S' = 3 n_gears + 1.
    """
    S = stage.shape[1]
    o = MO * (S // N_MODES)  # (M_o, gear 1), the last state kept (the open mode is the last)
    k = o + 1
    init = jnp.concatenate([init[:o], jnp.min(init[o:], axis=0, keepdims=True)])
    return (stage[:, :k], xs._replace(trac=xs.trac[:, :, :k]),
            dconsts._replace(D=dconsts.D[:k, :k]), init)


def solve_dp(dt_M, dt_G, stage, xs, consts, dconsts, init, mask, first=False, fast=None):
    """Run the Level 1 DP (`dp.viterbi`, or `dp.viterbi_first` if ``first``) with the fast
    relaxation on the open-merged states (`merge_open`) when every configuration has dt_M ==
    dt_G, the structured one on every state otherwise. Both are exact; the tests compare them
    with the dense matrix. ``fast`` (static): True / False picks one when the caller knows
    (under `vmap` a `lax.cond` on batched values runs both branches); None decides on the
    values (`lax.cond`: only one runs outside `vmap`). States are the full DP's indices.
    """
    f = dp.viterbi_first if first else dp.viterbi

    def fast_dp():
        st, x, dc, ini = merge_open(stage, xs, dconsts, init)
        return f(st, fast_transition(x, dc), ini, mask)

    if fast is not None:
        return fast_dp() if fast else f(stage, structured_transition(xs, consts), init, mask)
    fast = jnp.all(jnp.asarray(dt_M) == jnp.asarray(dt_G))
    return jax.lax.cond(fast, fast_dp,
                        lambda: f(stage, structured_transition(xs, consts), init, mask))


def braking_loss(vp: VehicleParams, H, P_d, dt):
    """(3, S) J: what a switch into each state loses of one braking step's recuperation.

    A switch opens the driveline for tau (eq. 12; rows: tau = dt_M for a mode switch, dt_G
    for a gear switch, the larger for both, as `switching.traction_cost_table`). Braking
    (P_d < 0), the service brakes then take the demand: for min(tau, dt) the state's
    Hamiltonian H gives way to the open mode's, a loss of max(0, H_open - H) per second (a
    hybrid's recuperation, worth -lambda_b P_bi). The traction-interruption cost A20-A22 prices
    the speed a switch loses to road load, not this; without it Level 1 downshifts through
    braking as if it recuperated all the way (RegionalDelivery: 2.6 MJ over its switches).
    Zero driving, into the open mode and into states that cannot run.
    H: (4, G) the step's Hamiltonian (W, +inf where infeasible); P_d: () W; dt: s."""
    H_open = jnp.min(H[MO])
    ok = jnp.isfinite(H) & jnp.isfinite(H_open) & (P_d < 0)
    lost = jnp.where(ok, jnp.maximum(H_open - jnp.where(ok, H, 0.0), 0.0), 0.0).reshape(-1)
    return jnp.minimum(sw.open_times(vp), dt)[:, None] * lost[None, :]


def transition_cost(vp: VehicleParams, s_from, s_to, v, grade, lam, params: sw.SwitchCostParams,
                    extra=None):
    """Switching cost (J) of s_from -> s_to at one step (scalars; broadcasts over states).

    The same cost as `switching.switch_cost_matrix` (with its `extra`, (3, S)), evaluated for
    one pair of states.
    """
    n_g = vp.gear_ratio.shape[-1]
    m0, g0 = s_from // n_g, s_from % n_g
    m1, g1 = s_to // n_g, s_to % n_g
    dtype = jnp.result_type(v, vp.I_e, float)
    ce = jnp.asarray(ENGINE_CONNECTED, dtype)
    cm = jnp.asarray(MOTOR_CONNECTED, dtype)
    w = vp.gear_ratio * vp.r_d * v
    E = sw.sync_energy(vp, ce[m0], cm[m0], w[g0], ce[m1], cm[m1], w[g1], params.averaged)
    trac = sw.traction_cost_table(vp, v, grade, params)  # (3, S)
    trac = trac if extra is None else trac + extra
    dm, dg = m0 != m1, g0 != g1
    t = jnp.where(dm & dg, trac[2, s_to], jnp.where(dm, trac[0, s_to], trac[1, s_to]))
    c = -lam * E + jnp.where(dm | dg, t, 0.0)
    return jnp.where(dm | dg, params.weight * c, 0.0)


# --------------------------------------------------------------------------------- tables
class DPInputs(NamedTuple):
    """What the Level 1 DP needs of one prediction at one costate trace (`dp_inputs`)."""

    P_d: jax.Array  # (T,) W
    stage: jax.Array  # (T, S) J
    xs: TransitionInputs  # (T, ...)
    consts: TransitionConsts
    dconsts: DenseConsts
    none_feasible: jax.Array  # (T,) bool
    lam: jax.Array  # (T,)
    brake: jax.Array  # (T, 3, S) J, `braking_loss`


def dp_inputs(vp, P_d, v, grade, lam, dt, params, trac=None, fixed=None) -> DPInputs:
    """The DP's inputs; trac: `traction_table(vp, v, grade, params)` and fixed:
    `powersplit.fixed_split(vp, P_d, v)` if already at hand (neither depends on lam).
    Only the Hamiltonian H of the split table is kept (the path's split is evaluated again
    along the path by `_result`: keeping every state's powers costs more than that)."""
    T = P_d.shape[0]
    lam = jnp.broadcast_to(jnp.asarray(lam, P_d.dtype), (T,))
    H_table = hamiltonian_H(vp, P_d, v, lam, fixed)
    H = H_table.reshape(T, -1)
    none = ~jnp.any(jnp.isfinite(H), axis=1)
    stage = jnp.where(none[:, None], 0.0, H * dt)
    if trac is None:
        trac = traction_table(vp, v, grade, params)
    xs = jax.vmap(transition_inputs, in_axes=(None, 0, 0, 0, None, 0))(vp, v, grade, lam,
                                                                       params, trac)
    brake = jax.vmap(braking_loss, in_axes=(None, 0, 0, None))(vp, H_table, P_d, dt)
    xs = xs._replace(trac=xs.trac + params.weight * brake)
    consts = transition_consts(vp, params.averaged)
    dconsts = dense_consts(vp, params.averaged)
    return DPInputs(P_d, stage, xs, consts, dconsts, none, lam, brake)


def _init_cost(init_mode, init_gear, S, n_g, dtype):
    s0 = init_mode * n_g + init_gear
    onehot = jnp.where(jnp.arange(S) == s0, 0.0, jnp.inf).astype(dtype)
    return jnp.where(init_mode < 0, jnp.zeros(S, dtype), onehot)


def _result(vp, tb: DPInputs, path, start, v, grade, dt, mask, params,
            switch_costs=True) -> Level1Result:
    """The path's decisions and powers; switch_costs: a bool () not batched, or True: where it
    is False, switch_cost is 0 and cost counts the stages only (a caller that needs neither
    skips their evaluation along the path)."""
    n_g = vp.gear_ratio.shape[-1]
    mode, gear = path // n_g, path % n_g
    sp = jax.vmap(split_state, in_axes=(None, 0, 0, 0, 0, 0))(vp, tb.P_d, v, tb.lam, mode, gear)
    prev = jnp.concatenate([start[None], path[:-1]])

    def costs():
        sc = jax.vmap(transition_cost, in_axes=(None, 0, 0, 0, 0, 0, None, 0))(
            vp, prev, path, v, grade, tb.lam, params, tb.brake
        )
        return jnp.where(mask, sc, 0.0)

    if switch_costs is True:
        sc = costs()
    else:
        sc = jax.lax.cond(switch_costs, costs, lambda: jnp.zeros_like(sp.H))
    Hk = sp.H
    stage = jnp.where(tb.none_feasible, 0.0, Hk * dt)
    cost = jnp.sum(jnp.where(mask, stage, 0.0)) + jnp.sum(sc)
    mprev, gprev = prev // n_g, prev % n_g
    z = lambda a: jnp.where(mask, a, 0.0)  # noqa: E731
    return Level1Result(
        mode=mode.astype(jnp.int32),
        gear=gear.astype(jnp.int32),
        state=path.astype(jnp.int32),
        P_b=z(sp.P_b),
        P_e=z(sp.P_e),
        P_m=z(sp.P_m),
        P_f=z(sp.P_f),
        P_brake=z(sp.P_brake),
        H=z(Hk),
        w=z(sp.w),
        switch_cost=sc,
        cost=cost,
        n_mode_switches=jnp.sum(mask & (mode != mprev)).astype(jnp.int32),
        n_gear_switches=jnp.sum(mask & (gear != gprev)).astype(jnp.int32),
        n_infeasible=jnp.sum(mask & tb.none_feasible).astype(jnp.int32),
    )


# ------------------------------------------------------------------------------ full horizon
def level1_kernel(vp, P_d, v, grade, lam, dt, mask, init_mode, init_gear, params, fast=None,
                  trac=None, switch_costs=True, fixed=None, path_of=None):
    """The kernel of `level1_full` (its inputs not checked, a pure function to jit or vmap):
    the DP's inputs (`dp_inputs`), the DP (`solve_dp`) and the path's decisions and powers
    (`Level1Result`). fast, trac, fixed: as `solve_dp` and `dp_inputs` take them;
    switch_costs: whether the path's switching costs are evaluated; path_of: None, or a
    function of the DP's path (T,) of states giving the path whose decisions and costs are
    returned (at this costate)."""
    TRACES["level1_full"] += 1
    tb = dp_inputs(vp, P_d, v, grade, lam, dt, params, trac, fixed)
    S = tb.stage.shape[1]
    n_g = S // N_MODES
    init = _init_cost(init_mode, init_gear, S, n_g, tb.stage.dtype)
    r = solve_dp(vp.dt_M, vp.dt_G, tb.stage, tb.xs, tb.consts, tb.dconsts, init, mask,
                 fast=fast)
    path = r.path if path_of is None else path_of(r.path)
    return _result(vp, tb, path, r.start, v, grade, dt, mask, params, switch_costs)


_level1_kernel_jit = jit(level1_kernel)


def _check_inputs(vp, P_d, v, grade, mask):
    check_vehicle(vp)
    gr = vp.gear_ratio
    if not isinstance(gr, jax.core.Tracer):
        g = np.asarray(gr)
        if g.ndim and np.any(np.diff(g, axis=-1) >= 0):
            raise ValueError("gear_ratio: must decrease with the gear number (gear 1 lowest)")
    shapes = {np.shape(a) for a in (P_d, v, grade) if a is not None}
    if len(shapes) != 1:
        raise ValueError(f"P_d, v, grade: must have the same shape (got {sorted(shapes)})")
    if mask is not None and np.shape(mask) != np.shape(P_d):
        raise ValueError(f"mask: shape {np.shape(mask)} differs from P_d {np.shape(P_d)}")


def _defaults(vp, P_d, mask, init_mode, init_gear, params):
    """The host API's defaults; the switching costs validated and typed as the vehicle
    (`switching.checked_params`, as `simulate` does: new values never recompile)."""
    if mask is None:
        mask = jnp.ones(jnp.shape(P_d), bool)
    if init_mode is None:
        init_mode, init_gear = -1, 0
    params = sw.checked_params(params, np.asarray(vp.mass).dtype)
    return mask, jnp.asarray(init_mode, jnp.int32), jnp.asarray(init_gear, jnp.int32), params


def level1_full(
    vp: VehicleParams,
    P_d,
    v,
    grade,
    lam,
    dt,
    mask=None,
    init_mode=None,
    init_gear=0,
    params: sw.SwitchCostParams | None = None,
) -> Level1Result:
    """Level 1 over the full horizon: Hamiltonians, switching costs and the Viterbi DP.

    P_d: (T,) driveline power demand (W); v: (T,) speed (m/s); grade: (T,) rise/run; lam: ()
    or (T,) lambda_b (piecewise constant from Level 2); dt: () step (s); mask: (T,) bool or
    None (False = padded step); init_mode, init_gear: the state before step 0 (mode index,
    gear index), or init_mode None / -1 for a free start; params: `SwitchCostParams`.
    Returns `Level1Result` (T,). Jitted; new array values do not recompile.
    """
    _check_inputs(vp, P_d, v, grade, mask)
    mask, im, ig, params = _defaults(vp, P_d, mask, init_mode, init_gear, params)
    return _level1_kernel_jit(vp, P_d, v, grade, lam, dt, mask, im, ig, params)


# --------------------------------------------------------------------------- receding horizon
def _level1_mpc(vp, P_d, v, grade, lam, dt, mask, init_mode, init_gear, params, horizon):
    TRACES["level1_mpc"] += 1
    tb = dp_inputs(vp, P_d, v, grade, lam, dt, params)
    T, S = tb.stage.shape
    n_g = S // N_MODES
    N = horizon
    pad = lambda a: jnp.concatenate([a, jnp.zeros((N,) + a.shape[1:], a.dtype)])  # noqa: E731
    stage_p = pad(tb.stage)
    mask_p = jnp.concatenate([mask, jnp.zeros(N, bool)])
    xs_p = jax.tree_util.tree_map(pad, tb.xs)
    init0 = _init_cost(init_mode, init_gear, S, n_g, tb.stage.dtype)

    def step(carry, k):
        prev, started = carry
        win = lambda a: jax.lax.dynamic_slice_in_dim(a, k, N)  # noqa: E731
        init = jnp.where(started, jnp.where(jnp.arange(S) == prev, 0.0, jnp.inf), init0)
        s0, _ = solve_dp(
            vp.dt_M,
            vp.dt_G,
            win(stage_p),
            jax.tree_util.tree_map(win, xs_p),
            tb.consts,
            tb.dconsts,
            init,
            win(mask_p),
            first=True,
        )
        s = jnp.where(mask[k], s0, prev)
        return (s, started | mask[k]), s

    s_init = jnp.where(init_mode < 0, 0, init_mode * n_g + init_gear)
    (_, _), path = jax.lax.scan(step, (s_init, init_mode >= 0), jnp.arange(T))
    first_valid = jnp.argmax(mask)
    start = jnp.where(init_mode < 0, path[first_valid], s_init)
    return _result(vp, tb, path, start, v, grade, dt, mask, params)


_level1_mpc_jit = jit(_level1_mpc, static_argnames=("horizon",))


def level1_mpc(
    vp: VehicleParams,
    P_d,
    v,
    grade,
    lam,
    dt,
    mask=None,
    init_mode=None,
    init_gear=0,
    params: sw.SwitchCostParams | None = None,
    *,
    horizon: int,
) -> Level1Result:
    """Level 1 as receding-horizon control (MPC): at each step k solve the DP over steps
    k .. k + horizon - 1 from the current state, apply its first decision, repeat.

    Same arguments and result as `level1_full`; ``horizon`` (static) is the number of samples
    N of the window (steps past the end are padding). A horizon of at least T samples gives
    the full-horizon solution.
    """
    if int(horizon) < 1:
        raise ValueError(f"horizon: must be >= 1 sample (got {horizon})")
    _check_inputs(vp, P_d, v, grade, mask)
    mask, im, ig, params = _defaults(vp, P_d, mask, init_mode, init_gear, params)
    return _level1_mpc_jit(vp, P_d, v, grade, lam, dt, mask, im, ig, params, horizon=int(horizon))


# ----------------------------------------------------------------------------------- batched
def _level1_batch(vps, P_d, v, grade, mask, lam, dt, init_mode, init_gear, params):
    TRACES["level1_batch"] += 1
    R, T = P_d.shape
    n_v = jax.tree_util.tree_leaves(vps)[0].shape[0]
    L = lam.shape[0]
    # one flat batch over (route, vehicle, lambda_b), row-major, with every input gathered to
    # it: vmapped over lambda_b with the route's inputs unbatched, XLA's CPU fusion evaluated
    # the Hamiltonian table again inside each of the switching-cost tables' consumers (about
    # ten times the work per configuration)
    ri, vi, li = (a.reshape(-1) for a in np.indices((R, n_v, L)))
    vb = jax.tree_util.tree_map(lambda a: a[vi], vps)
    P_db, v_b, g_b, m_b, lam_b = P_d[ri], v[ri], grade[ri], mask[ri], lam[li]

    def one(vp, P_d, v, grade, lam):
        return dp_inputs(vp, P_d, v, grade, lam, dt, params)

    tb = jax.vmap(one)(vb, P_db, v_b, g_b, lam_b)
    last = lambda a: jnp.moveaxis(a, 0, -1)  # noqa: E731
    stage = last(tb.stage)  # (T, S, B)
    S = stage.shape[1]
    n_g = S // N_MODES
    xs = TransitionInputs(scale=last(tb.xs.scale), trac=last(tb.xs.trac))
    consts = jax.tree_util.tree_map(last, tb.consts)
    dconsts = jax.tree_util.tree_map(last, tb.dconsts)
    init = _init_cost(init_mode, init_gear, S, n_g, stage.dtype)
    r = solve_dp(vb.dt_M, vb.dt_G, stage, xs, consts, dconsts, init[:, None], last(m_b))

    def res(vp, tb1, path1, start1, v1, grade1, mask1):
        return _result(vp, tb1, path1, start1, v1, grade1, dt, mask1, params)

    out = jax.vmap(res)(vb, tb, last(r.path), r.start, v_b, g_b, m_b)
    return jax.tree_util.tree_map(lambda a: a.reshape((R, n_v, L) + a.shape[1:]), out)


_level1_batch_jit = jit(_level1_batch)


def level1_batch(
    vps: VehicleParams,
    P_d,
    v,
    grade,
    mask,
    lam,
    dt,
    init_mode=None,
    init_gear=0,
    params: sw.SwitchCostParams | None = None,
) -> Level1Result:
    """Full-horizon Level 1 for routes x vehicles x lambda_b in one jitted call.

    vps: `VehicleParams` stacked over V vehicles (`stack_vehicles`); P_d, v, grade, mask: (R, T)
    padded routes; lam: (L,) or (L, T) costates; dt: () s; init_mode/init_gear and params as in
    `level1_full` (shared by the batch). Returns `Level1Result` with leading axes (R, V, L).
    The DP runs with the batch on the last axis (fast on CPU). New values never recompile.
    """
    if np.ndim(P_d) != 2:
        raise ValueError(f"P_d: expected (routes, T), got shape {np.shape(P_d)}")
    _check_inputs(vps, P_d, v, grade, mask)
    mask, im, ig, params = _defaults(vps, P_d, mask, init_mode, init_gear, params)
    lam = jnp.asarray(lam)
    if lam.ndim not in (1, 2):
        raise ValueError(f"lam: expected (L,) or (L, T), got shape {lam.shape}")
    return _level1_batch_jit(vps, P_d, v, grade, mask, lam, dt, im, ig, params)


__all__ = [
    "DenseConsts",
    "Level1Result",
    "TransitionConsts",
    "TransitionInputs",
    "braking_loss",
    "dense_consts",
    "fast_transition",
    "level1_batch",
    "level1_full",
    "level1_mpc",
    "relax_same_open_time",
    "relax_structured",
    "solve_dp",
    "structured_transition",
    "traction_table",
    "transition_consts",
    "transition_cost",
    "transition_inputs",
    "TRACES",
]
