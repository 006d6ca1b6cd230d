"""dp-bound's dynamic program: the global optimum of problem (21) with the velocity fixed to
the Level 3 prediction, over (E_b grid x mode x gear) with Level 1's switching costs.

`bound_tables` gives each step's candidates (M_c's split at `dp_candidate_lams` costates, the
other modes' once) and switching costs; `bound_dp` runs the backward DP to a goal E_b(tf)
with a terminal penalty and rolls the path out forward from the exact E_b(t0) (the generic
Viterbi's relaxation, `dp.relax_dense`, over the states); `bound_pieces` turns the DP's path
into the pieces its plan keeps (`plan.make_plan`). The strategy (attempts, plant runs) is
`strategies.run_dp_bound`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, NamedTuple

import jax
import jax.numpy as jnp

from . import dp
from . import powertrain as pt
from . import switching as sw
from .levels import battery as l2
from .levels import level1 as l1
from .levels import powersplit as ps
from .levels import velocity as l3
from .plan import init_state

if TYPE_CHECKING:
    from .strategies import Options


BIG = 1e15  # "infeasible" in the DP bound (finite, so that interpolation stays finite)


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

    m_init, g_init = init_state(pred)
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

