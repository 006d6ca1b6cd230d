"""Plans that the plant follows: the battery-power trim on M_c steps, Level 2's pieces as
targets, and the plant-drift compensation (strategies.trim_battery_power, piece_targets,
compensate), on the short track at 25 t against plain loops."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxems import plant as pl
from jaxems import powertrain as pt
from jaxems import strategies as S
from jaxems import switching as sw
from jaxems.io import load_route
from jaxems.levels import powersplit as ps
from jaxems.params import load_vehicle

VP = load_vehicle().replace(mass=25000.0)
ROUTE = load_route("short_track")
N = S.steps_for_batch(ROUTE, VP)
PRED = jax.jit(lambda r, v: S.level3(r, v, 1.0, N))(ROUTE, VP)
R1 = jax.jit(lambda v, p, lam: S._level1(v, p, lam, 1.0, sw.SwitchCostParams()))(VP, PRED, -2.0)
T = PRED.v.shape[0]
MID = int(np.sum(np.asarray(PRED.mask))) // 2
PID = jnp.asarray((np.arange(T) >= MID).astype(np.int32))
trim = jax.jit(lambda target: S.trim_battery_power(VP, PRED, R1.mode, R1.gear, R1.P_b, PID,
                                                    target, 1.0))


def loop_range(k):
    """The plant's battery-power range of the plan's state at step k (the trim's bounds)."""
    r = pl.state_ranges(VP, R1.mode[k], R1.gear[k], PRED.v[k])
    P_d = float(PRED.P_d[k])
    lo = float(ps.pb_of_pm(VP, r, max(-float(r.m_lim), P_d - float(r.e_hi))))
    hi = float(ps.pb_of_pm(VP, r, min(float(r.m_lim), P_d - float(r.e_lo))))
    P = float(R1.P_b[k])
    return min(lo, P), max(hi, P), bool(r.ok)


def piece_energy(P_b):
    sync = np.asarray(pl.path_sync_energy(VP, R1.mode, R1.gear, PRED.v))
    dE = np.where(np.asarray(PRED.mask),
                  -np.asarray(pt.battery_internal(VP, jnp.asarray(P_b))) - sync, 0.0)
    pid = np.asarray(PID)
    return np.array([dE[pid == p].sum() for p in range(2)])


@pytest.mark.parametrize("target", [(0.0, 0.0), (-3e5, 2e5), (4e5, -6e5), (-5e7, 5e7)])
def test_trim_meets_each_piece_target_within_the_states_ranges(target):
    target = np.asarray(target)
    got = np.asarray(trim(jnp.asarray(target)))
    mode = np.asarray(R1.mode)
    adj = np.zeros(T, bool)
    lo = np.empty(T)
    hi = np.empty(T)
    for k in range(T):
        lo[k], hi[k], ok = loop_range(k)
        adj[k] = ok and mode[k] == ps.MC and bool(PRED.mask[k])
    assert adj[:MID].any() and adj[MID:].any()  # both pieces have M_c steps to trim
    # elsewhere the plan's battery power is untouched; on M_c steps it stays in range
    np.testing.assert_array_equal(got[~adj], np.asarray(R1.P_b)[~adj])
    assert np.all(got[adj] >= lo[adj] - 1e-6) and np.all(got[adj] <= hi[adj] + 1e-6)
    # each piece meets its target where the range allows, else sits at the range's end
    at_lo, at_hi = np.where(adj, lo, got), np.where(adj, hi, got)
    e_lo, e_hi = piece_energy(at_lo), piece_energy(at_hi)  # most charge / most discharge
    e = piece_energy(got)
    pid = np.asarray(PID)
    for p in range(2):
        if e_hi[p] <= target[p] <= e_lo[p]:
            assert abs(e[p] - target[p]) < 1.0, p
        elif target[p] > e_lo[p]:
            np.testing.assert_allclose(got[adj & (pid == p)], lo[adj & (pid == p)], atol=1e-6)
        else:
            np.testing.assert_allclose(got[adj & (pid == p)], hi[adj & (pid == p)], atol=1e-6)


def test_compensate_raises_each_target_by_the_drift_over_its_stretch():
    L = float(PRED.length)
    drift = S.Drift(s=jnp.linspace(0.0, L, T + 1), dE=-2.0 * jnp.linspace(0.0, L, T + 1))
    bnd = jnp.asarray([0, MID, T])
    pid, target = S.compensate((PID, jnp.zeros(2)), PRED, bnd, drift)
    s_mid = float(PRED.s[MID])
    np.testing.assert_allclose(np.asarray(target), [2.0 * s_mid, 2.0 * (L - s_mid)], rtol=1e-9)
    np.testing.assert_array_equal(np.asarray(pid), np.asarray(PID))


def test_piece_targets_map_steps_to_level2_pieces():
    class C2:  # the fields piece_targets reads, as Level 2 returns them (K = 3)
        lam_lo = jnp.zeros(3)
        boundaries = jnp.asarray([0, 5, 9, 12])
        E_bnd = jnp.asarray([2e6, 0.0, 4e6, 2e6])

    pid, target = S.piece_targets(C2, 12)
    np.testing.assert_array_equal(np.asarray(pid), [0] * 5 + [1] * 4 + [2] * 3)
    np.testing.assert_allclose(np.asarray(target), [-2e6, 4e6, -2e6])
