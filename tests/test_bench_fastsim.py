"""benchmarks/bench_fastsim.py: the Level 3 trace as a FASTSim cycle (FASTSim itself optional)."""

import numpy as np
import pytest

from jaxems.params import load_vehicle
from jaxems.route import Row, elevation, route_from_rows
from repo_scripts import load_script

bf = load_script("benchmarks/bench_fastsim.py")


def _route():
    # standing start, an 8 % climb, a 9 % descent, a stop, a 3 % climb, a final stop
    data = [(0, 0, 0, 5), (10, 60, 0, 0), (400, 60, 8, 0), (900, 40, -9, 0), (1300, 0, 0, 20),
            (1310, 80, 3, 0), (2500, 30, 0, 0), (2700, 80, -4, 0), (3500, 0, 0, 10)]
    return route_from_rows([Row(*r, line=i + 2) for i, r in enumerate(data)], ds=10.0,
                           bucket=512)


ROUTE = _route()
PRED = CYCLE = None  # Level 3 on ROUTE and its cycle: set by the module fixture, not at import


@pytest.fixture(scope="module", autouse=True)
def _prediction():
    global PRED, CYCLE
    PRED = bf.level3_prediction(ROUTE, load_vehicle().replace(mass=20000.0))
    CYCLE = bf.fastsim_cycle(PRED)


def test_cycle_grid_and_speeds():
    K = int(np.sum(np.asarray(PRED.mask)))
    t = CYCLE["time_seconds"]
    assert all(CYCLE[k].shape == (K + 1,) for k in CYCLE)
    np.testing.assert_allclose(t, np.arange(K + 1) * float(PRED.dt))
    assert t[-1] >= float(PRED.trip_time) > t[-2]
    v = CYCLE["speed_meters_per_second"]
    assert np.all(v >= 0)
    np.testing.assert_allclose(v[:K], np.asarray(PRED.v_ref)[:K])
    assert v[0] == 0.0 and v[-1] == 0.0  # standing start, final stop
    assert np.max(v) <= 80 / 3.6 + 1e-9


def test_cycle_distance_and_rise_match_the_route():
    # FASTSim integrates distance with the mean of consecutive speeds and applies grade[i] to
    # the step ending at t_i: the trace must cover the route and climb its net elevation
    assert bf.trace_distance_m(CYCLE) == pytest.approx(float(PRED.length), abs=1.0)
    mask = np.asarray(ROUTE.mask)
    net_rise = float(np.asarray(elevation(ROUTE))[mask][-1])
    assert abs(net_rise) > 5.0
    assert bf.trace_rise_m(CYCLE) == pytest.approx(net_rise, abs=0.2)
    # grade one step early (grade[i] for the step after t_i) misses the net rise by > 1 m
    early = dict(CYCLE, grade=np.append(CYCLE["grade"][1:], 0.0))
    assert abs(bf.trace_rise_m(early) - net_rise) > 1.0


def test_cycle_rejects_a_batch():
    import jax

    batched = jax.tree_util.tree_map(lambda a: np.stack([a, a]), PRED)
    with pytest.raises(ValueError, match="one route"):
        bf.fastsim_cycle(batched)


def test_fastsim_drives_the_cycle():
    pytest.importorskip("fastsim")
    sd = bf.make_simdrive(CYCLE, bf.DEFAULT_VEHICLE)
    bf.drive(sd, balance=False)
    s = bf.fastsim_summary(sd)
    assert s["powertrain"] == "HEV"
    assert s["trace_met"]
    assert s["distance_m"] == pytest.approx(bf.trace_distance_m(CYCLE), rel=1e-9)
    assert s["fuel_MJ"] > 0


def test_time_fastsim_reports_the_cycle_rate():
    pytest.importorskip("fastsim")
    r = bf.time_fastsim(CYCLE, bf.DEFAULT_VEHICLE, repeats=1)
    cycle_s = CYCLE["time_seconds"][-1]
    assert r["sim_s_per_wall_s"] == pytest.approx(cycle_s / r["wall_s"])
    assert r["distance_m"] == pytest.approx(bf.trace_distance_m(CYCLE), rel=1e-9)
    assert isinstance(r["soc_balanced"], bool)
