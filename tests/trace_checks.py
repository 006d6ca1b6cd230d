"""A check on a plant's time series that several test modules make."""

import numpy as np
import pytest


def assert_trace_closes(beta, E_max, P_f, P_b, counted, sync_f, sync_b, E_b, E_end, fuel,
                        fuel_abs=0.0, msg=""):
    """The time series accounts for every joule of the run's totals: the fuel (J) is the fuel
    power P_f over the time each step counts (`counted`, s) plus the synchronisation energy
    drawn from fuel (sync_f), and each step's battery energy (E_b, then E_end after the last)
    follows from the last by its internal power P_b + beta P_b^2 over that time and the
    synchronisation energy drawn from the battery (sync_b), within [0, E_max]."""
    P_f, P_b, span, sync_f, sync_b, E_b = (np.asarray(x, np.float64) for x in
                                           (P_f, P_b, counted, sync_f, sync_b, E_b))
    total = np.sum(P_f * span) + np.sum(sync_f)
    assert total == pytest.approx(fuel, rel=1e-10, abs=fuel_abs), msg
    E = np.append(E_b, E_end)
    after = np.clip(E[:-1] - (P_b + beta * P_b * P_b) * span - sync_b, 0.0, E_max)
    np.testing.assert_allclose(E[1:], after, rtol=1e-12, atol=1e-6, err_msg=msg)
