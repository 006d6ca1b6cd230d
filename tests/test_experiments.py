"""experiments/table7.py, table8.py, traces.py, charge_grid.py, option_grid.py, resolution.py,
mpc_gap.py, random_routes.py and plan_tracking.py: JSON structure, row arithmetic, figures.

Cheap configurations on the short track (it stands in for a VECTO route in table8 here); the
scripts run in-process so that they share compilations with each other and with
tests/test_cli_simulate.py (conventional, baseline and multilevel with n_iter = 2, 25 t).
"""

import json

import numpy as np
import pytest

from jaxems.io import load_route
from jaxems.levels.velocity import predict_velocity
from jaxems.params import load_vehicle, with_overrides
from jaxems.strategies import simulate
from repo_scripts import load_script

LHV_J_PER_KG, DENSITY_KG_PER_L = 42.8e6, 0.832  # data/vehicles/reference_truck.toml [fuel]
VP25 = with_overrides(load_vehicle(), mass_kg=25000.0)


def _script(name):
    return load_script(f"experiments/{name}.py", f"exp_{name}")


table7, table8, traces = _script("table7"), _script("table8"), _script("traces")
plan_tracking = _script("plan_tracking")  # loaded once: its jitted split compiles once


def main_json(script, args, capsys):
    """(the JSON object, stderr) of script.main(args + ["--json"]), which exits 0: stdout
    holds exactly one JSON object, progress goes to stderr."""
    code = script.main([*args, "--json"])
    out, err = capsys.readouterr()
    assert code == 0, err
    return json.loads(out), err


@pytest.fixture(scope="module")
def t7():
    return table7.run_table("short_track", 25000.0, ["conventional", "multilevel"], n_iter=2)


def test_table7_json_is_one_object(capsys):
    d, err = main_json(table7, ["--strategies", "conventional,multilevel"], capsys)
    assert "table7: conventional" in err and "table7: multilevel" in err
    labels = [r["label"] for r in d["rows"]]
    assert labels == ["non-hybrid", "iteration 0", "iteration 1"]
    for r in d["rows"]:
        for k in ("strategy", "fuel_J", "fuel_l_per_100km", "delta_Eb_J", "fuel_corrected_J",
                  "lambda_b", "reduction_pct", "paper_J_MJ", "paper_reduction_pct"):
            assert k in r, k
    assert [r["paper_J_MJ"] for r in d["rows"]] == [16.8, 7.91, 7.90]
    assert d["mass_kg"] == 25000.0 and d["route"] == "short_track"


def test_table7_rows_match_runs(t7):
    rows = t7["rows"]
    conv, it0, it1 = rows
    vp = with_overrides(load_vehicle("reference_truck"), mass_kg=25000.0)
    # the last iteration is the multilevel run itself (same compilation: n_iter is the same)
    res = simulate("short_track", vp, "multilevel", n_iter=2).as_dict()
    for k in ("fuel_J", "delta_Eb_J", "lambda_b", "fuel_corrected_J", "mode_switches"):
        assert it1[k] == pytest.approx(res[k], rel=1e-12), k
    assert (it0["iteration"], it1["iteration"], conv["iteration"]) == (0, 1, None)
    for r in rows:
        assert r["fuel_corrected_J"] == pytest.approx(r["fuel_J"] + r["lambda_b"] * r["delta_Eb_J"])
        assert r["reduction_pct"] == pytest.approx(
            100 * (1 - r["fuel_corrected_J"] / conv["fuel_corrected_J"]))
        litres = r["fuel_J"] / LHV_J_PER_KG / DENSITY_KG_PER_L
        assert r["fuel_l_per_100km"] == pytest.approx(litres / (1055 / 1e5), rel=1e-9)
    assert conv["reduction_pct"] == 0.0 and conv["delta_Eb_J"] == 0.0
    assert it0["lambda_b"] < 0 and it1["lambda_b"] < 0
    # the hybrid saves energy on the short track (the paper: about half)
    assert it0["reduction_pct"] > 20 and it1["reduction_pct"] > 20
    text = table7.format_table(t7)
    assert text.count("\n") == 2 + len(rows)
    assert "iteration 0" in text and "16.80" in text and "52.9" in text


def test_level2_traces_match_iteration_0(t7, tmp_path):
    vp = with_overrides(load_vehicle("reference_truck"), mass_kg=25000.0)
    res = simulate("short_track", vp, "multilevel", n_iter=2)
    # iteration 0's Level 2 runs on Level 3 at the constant engine speed (predict_velocity)
    l2 = traces.level2_traces(vp, predict_velocity(load_route("short_track"), vp, dt=1.0))
    assert l2["lambda_b"] == pytest.approx(float(np.asarray(res.extra.lambda_b)[0]), rel=1e-6)
    E0 = 0.5 * float(vp.E_b_max)
    assert l2["E_b"][0] == pytest.approx(E0)
    assert np.all((l2["E_b"] >= -1.0) & (l2["E_b"] <= float(vp.E_b_max) + 1.0))
    assert set(np.unique(l2["mode"])) <= {0, 1, 2, 3}
    assert np.all((l2["gear"] >= 1) & (l2["gear"] <= 12))
    path = tmp_path / "fig.png"
    traces.plot_run(res, vp, "test", path, l2)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_traces_main_writes_figure(tmp_path, capsys):
    assert traces.main(["--out", str(tmp_path), "--figures", "A3"]) == 0  # multilevel, n_iter 2
    out = capsys.readouterr().out
    assert (tmp_path / "figA3.png").stat().st_size > 10_000 and "A3: multilevel" in out
    assert traces.main(["--figures", "A9"]) == 1


def test_table8_json_structure(capsys):
    d, err = main_json(table8, ["--routes", "short_track", "--strategies",
                                "conventional,baseline"], capsys)
    assert "table8: short_track" in err
    assert d["mass_kg"] == 20000.0
    rows = d["rows"]
    assert [(r["route"], r["strategy"]) for r in rows] == [
        ("short_track", "conventional"), ("short_track", "baseline")]
    conv, base = rows
    for r in rows:
        for k in ("fuel_J", "fuel_l_per_100km", "delta_Eb_J", "fuel_corrected_J",
                  "fuel_corrected_l_per_100km", "saving_pct", "lambda_b", "status"):
            assert k in r, k
        assert r["fuel_corrected_l_per_100km"] == pytest.approx(
            r["fuel_l_per_100km"] * r["fuel_corrected_J"] / r["fuel_J"])
    assert conv["saving_pct"] == 0.0
    assert base["saving_pct"] == pytest.approx(
        100 * (base["fuel_corrected_J"] / conv["fuel_corrected_J"] - 1))
    assert [p["fuel_l_per_100km"] for p in d["paper"]] == [33.0, 31.1, 30.7]
    text = table8.format_table(d)
    assert "baseline" in text and "33.0 l/100 km" in text and "-7.0 %" in text
    # the reference's own saving prints as +0.0 (not a negative zero)
    conv_line = next(x for x in text.splitlines() if x.startswith("short_track") and
                     "conventional" in x)
    assert conv_line.split()[4] == "+0.0"


def test_table8_bad_input_fails_before_running(capsys):
    assert table8.main(["--strategies", "conventional,greedy"]) == 1
    assert "unknown 'greedy'" in capsys.readouterr().err
    assert table8.main(["--routes", "short_track,no_such_route"]) == 1
    err = capsys.readouterr().err
    assert "no such route file" in err and "table8: short_track" not in err
    assert table7.main(["--mass", "-1"]) == 1
    assert "mass_kg" in capsys.readouterr().err


def test_eco_velocity_bad_input_fails_before_running(capsys):
    eco = _script("eco_velocity")
    assert eco.main(["--routes", "short_track,no_such_route"]) == 1
    err = capsys.readouterr().err
    assert "no such route file" in err and "eco: short_track" not in err
    assert eco.main(["--mass", "-1"]) == 1
    assert "mass_kg" in capsys.readouterr().err


def test_charge_grid_json_and_the_baselines_balance(capsys):
    """charge_grid: one row per (strategy, mass, soc0) with delta E_b in % of the battery; the
    A-ECMS, whose reference is the trip's start, ends the same energy from it at 30 and 50 %
    (the 25 t baseline shares its compilation with the tests above)."""
    grid = _script("charge_grid")
    d, err = main_json(grid, ["--strategies", "baseline", "--socs", "0.3,0.5"], capsys)
    assert "charge_grid: baseline" in err
    rows = d["rows"]
    assert [(r["strategy"], r["soc0"]) for r in rows] == [("baseline", 0.3), ("baseline", 0.5)]
    size = float(load_vehicle().E_b_max)
    for r in rows:
        assert r["mass_kg"] == 25000.0 and r["status"] == "ok"
        assert r["delta_Eb_pct"] == pytest.approx(100 * r["delta_Eb_J"] / size)
        assert r["sustained"] == (abs(r["delta_Eb_pct"]) <= 1.0)
    assert rows[0]["delta_Eb_J"] == pytest.approx(rows[1]["delta_Eb_J"], abs=1.0)
    assert "within 1 %: " in grid.format_table(d)
    assert grid.main(["--socs", "half"]) == 1
    assert "--socs: expected comma-separated numbers" in capsys.readouterr().err
    assert grid.main(["--socs", "1.5", "--strategies", "baseline"]) == 1
    assert "soc0: must be in [0, 1]" in capsys.readouterr().err


def test_option_grid_rows_are_the_runs_at_each_value(capsys):
    """option_grid: a row per (option value, route); the default value's figures are the
    plain run's (corrected fuel, charge, trip against Level 3; one compilation shared with the
    other modules' baseline at 25 t), the other value's differ; bad --set values named."""
    grid = _script("option_grid")
    d, err = main_json(grid, ["--strategy", "baseline", "--set", "ecms_horizon=1,3",
                              "--routes", "short_track", "--masses", "25000",
                              "--batteries", "4"], capsys)
    assert "option_grid: {'ecms_horizon': 1}" in err
    assert [r["options"] for r in d["rows"]] == [{"ecms_horizon": 1}, {"ecms_horizon": 3}]
    assert d["rows"][0]["fuel_corrected_J"] != d["rows"][1]["fuel_corrected_J"]
    row, r = d["rows"][1], simulate("short_track", VP25, "baseline")  # ecms_horizon 3: default
    assert row["runs"] == 1 and row["not_ok"] == 0 and row["route"] == "short_track"
    assert row["fuel_corrected_J"] == pytest.approx(r["fuel_corrected_J"], rel=1e-9)
    assert row["off_charge"] == int(abs(r["delta_Eb_J"]) > 0.01 * float(VP25.E_b_max))
    pct = 100 * (r["trip_time_s"] / r["level3_trip_time_s"] - 1)
    assert row["trip_pct_max"] == pytest.approx(pct, abs=1e-9)
    assert row["trip_long"] == int(pct > 1.0)
    assert "ecms_horizon=3" in grid.format_table(d) and "all" in grid.format_table(d)
    for bad, says in (["n_iter=2", "n_iter: not an option of baseline"],
                      ["ecms_horizon=0", "ecms_horizon: must be a finite number > 0"],
                      ["ecms_horizon", "expected NAME=VALUE"]):
        assert grid.main(["--strategy", "baseline", "--set", bad]) == 1
        assert says in capsys.readouterr().err, bad


def test_resolution_summary_against_plain_arithmetic(capsys):
    """resolution: corrected fuel per strategy and mass (the runs of charge_grid at half
    charge), medians, spreads and the checks' gaps mass by mass; the gaps' arithmetic on
    made-up rows, the JSON on the 25 t baseline (shared compilation) at two masses."""
    res = _script("resolution")
    masses = [1.0, 2.0, 3.0]
    fuel = {"multilevel": [103.0, 101.0, 110.0], "dp-bound": [100.0, 100.0, 100.0],
            "multilevel-mpc": [103.0, 102.01, 99.0]}
    rows = [{"strategy": s, "mass_kg": m, "fuel_corrected_J": f}
            for s, v in fuel.items() for m, f in zip(masses, v, strict=True)]
    strategies, gaps = res.summarise(rows, masses)
    assert strategies["multilevel"]["median_J"] == 103.0
    assert strategies["multilevel"]["spread_pct"] == pytest.approx(100 * 9.0 / 103.0)
    g = gaps["multilevel vs dp-bound"]
    np.testing.assert_allclose(g["gap_pct"], [3.0, 1.0, 10.0])
    assert (g["median_pct"], g["min_pct"], g["max_pct"]) == pytest.approx((3.0, 1.0, 10.0))
    np.testing.assert_allclose(gaps["multilevel-mpc vs multilevel"]["gap_pct"],
                               [0.0, 1.0, -10.0])
    assert res.summarise(rows[:3], masses)[1] == {}  # one strategy: no gap

    d, _ = main_json(res, ["--strategies", "baseline", "--offsets", "0,50"], capsys)
    assert d["masses"] == [25000.0, 25050.0] and d["gaps"] == {}
    runs = [simulate("short_track", with_overrides(load_vehicle(), mass_kg=m), "baseline")
            for m in d["masses"]]
    np.testing.assert_allclose(d["strategies"]["baseline"]["fuel_corrected_J"],
                               [r["fuel_corrected_J"] for r in runs], rtol=1e-12)
    assert "+50 kg" in res.format_table(d)
    assert res.main(["--offsets", "0,-5", "--strategies", "baseline"]) == 1
    assert "--offsets: expected distinct kilograms >= 0" in capsys.readouterr().err
    assert res.main(["--mass", "1,2", "--strategies", "baseline"]) == 1
    assert "--mass: expected one number" in capsys.readouterr().err


def test_random_routes_rows_are_runs_and_the_summary_their_arithmetic(capsys):
    """random_routes: each row is `simulate` on its route (rebuilt from the row's own rows) and
    mass; the fuel ratios are against the same route's conventional run, and the summary
    counts what the rows say; bad input is one line naming the option."""
    rr = _script("random_routes")
    d, err = main_json(rr, ["--n", "2", "--strategies", "conventional,multilevel"], capsys)
    assert "random_routes: route 1" in err
    rows = d["rows"]
    assert [(r["route"], r["strategy"]) for r in rows] == [
        (0, "conventional"), (0, "multilevel"), (1, "conventional"), (1, "multilevel")]
    for r in rows:
        route = rr.route_of(r["rows"])
        assert r["rows"][0] == [0.0, 0.0, 0.0, 5.0] and r["rows"][-1][1:] == [0.0, 0.0, 2.0]
        assert all(abs(x[2]) <= 8.0 for x in r["rows"])
        assert 15000.0 <= r["mass_kg"] <= 40000.0
        run = simulate(route, with_overrides(load_vehicle(), mass_kg=r["mass_kg"]),
                       r["strategy"])
        assert r["fuel_corrected_J"] == pytest.approx(run["fuel_corrected_J"], rel=1e-12)
        assert r["delta_Eb_pct"] == pytest.approx(100 * run["delta_Eb_J"] / 4e6, abs=1e-9)
        assert r["sustained"] == (abs(r["delta_Eb_pct"]) <= 1.0)
        conv = next(c for c in rows if c["route"] == r["route"]
                    and c["strategy"] == "conventional")
        assert r["fuel_ratio"] == pytest.approx(r["fuel_corrected_J"]
                                                / conv["fuel_corrected_J"])
    ml = [r for r in rows if r["strategy"] == "multilevel"]
    s = d["summary"]["multilevel"]
    assert (s["runs"], s["ok"]) == (2, sum(r["status"] == "ok" for r in ml))
    assert s["fuel_ratio_max"] == max(r["fuel_ratio"] for r in ml)
    assert s["off_charge"] == sum(abs(r["delta_Eb_pct"]) > 1.0 for r in ml)
    assert s["trip_beyond_target"] == sum(
        abs(r["trip_time_s"] - r["level3_trip_time_s"]) > 0.01 * r["level3_trip_time_s"]
        for r in ml)
    assert "multilevel" in rr.format_table(d)
    assert rr.main(["--n", "2", "--strategies", "multilevel"]) == 1
    assert "--strategies: conventional is the reference" in capsys.readouterr().err
    assert rr.main(["--n", "1", "--grade-max", "40"]) == 1
    assert "--grade-max: a gradient in % from 0 to 30" in capsys.readouterr().err


def test_mpc_gap_level1_at_a_given_costate_is_the_mpc(capsys):
    """mpc_gap: the MPC's Level 1 (`strategies.mpc_level1`) fed, by position, the costate trace
    of an MPC run reproduces that run (fuel, battery, switches, trip); bad horizons are one
    line naming --h1."""
    gap = _script("mpc_gap")
    vp = load_vehicle().replace(mass=25000.0)
    mpc = simulate("short_track", vp, "multilevel-mpc")
    got = gap.given_costate(gap.S.route_arg("short_track"), vp, mpc.trace.s, mpc.trace.lam, 5)
    for k in ("fuel_J", "delta_Eb_J", "mode_switches", "gear_switches", "trip_time_s"):
        assert float(np.asarray(got[k]).reshape(-1)[0]) == pytest.approx(mpc[k], rel=1e-12), k
    assert gap.main(["--h1", "0"]) == 1
    assert "--h1: expected comma-separated whole numbers >= 1" in capsys.readouterr().err
    assert gap.main(["--h1", "five"]) == 1


@pytest.mark.parametrize("strategy", ["multilevel", "dp-bound"])
def test_plan_tracking_counts_what_the_plan_asks_of_an_empty_battery(capsys, strategy):
    """plan_tracking on the short track at 25 t with 3 MJ (multilevel's plan asks 1.57 MJ of an
    empty battery on 22 steps, dp-bound's 0.09 MJ on 6; with 2 MJ, 0.35 MJ on 15 steps each
    until the trim split the pieces at the plans' excursions): one JSON object; the
    stretches' plant fuel sums to the trace's, which is the run's less the synchronisation
    energy the engine supplied (at most the run's), their steps at empty to the summary's and
    to its runs', whose energy asked is the summary's; every such step is one where the plan's
    battery is at empty and its own model draws from it, as a loop over the plan finds them;
    an unknown route is one line."""
    track = plan_tracking
    d, err = main_json(track, ["--route", "short_track", "--mass", "25000", "--battery-MJ", "3",
                               "--strategy", strategy, "--segment-km", "0.3"], capsys)
    assert f"plan_tracking: {strategy} on short_track" in err
    sm, segs, runs = d["summary"], d["segments"], d["runs"]
    assert sm["strategy"] == strategy and len(segs) == 4  # 1.05 km in stretches of 0.3
    assert 1e6 * sum(g["plant_fuel_MJ"] for g in segs) == pytest.approx(sm["trace_fuel_J"],
                                                                       rel=1e-9)
    assert sm["trace_fuel_J"] <= sm["fuel_J"] and sm["trace_fuel_J"] > 0.95 * sm["fuel_J"]
    assert sum(g["empty_steps"] for g in segs) == sm["empty_steps"] == sum(
        r["steps"] for r in runs)
    assert 1e6 * sum(r["asked_MJ"] for r in runs) == pytest.approx(sm["asked_at_empty_J"],
                                                                   rel=1e-9, abs=1e-3)
    assert sm["empty_steps"] > 0 and sm["asked_at_empty_J"] > 0
    vp = load_vehicle().replace(mass=25000.0, E_b_max=3e6)
    res = simulate("short_track", vp, strategy)
    plan = track.last_plan(res)
    dE = np.asarray(track.pn.steps_energy(vp, res.prediction, plan.mode, plan.gear, plan.P_b,
                                         1.0))
    mask = np.asarray(res.prediction.mask)
    n = sum(1 for k in range(mask.size)
            if mask[k] and plan.E_ref[k] <= track.EMPTY_J and dE[k] < -track.EMPTY_J)
    assert n == sm["empty_steps"]
    from jaxems.cli import script_main

    capsys.readouterr()
    assert script_main("plan_tracking", track.main, ["--route", "nowhere"]) == 1
    assert "plan_tracking: error: nowhere: no such route file" in capsys.readouterr().err


def test_control_map_refuses_a_gear_out_of_range(capsys):
    from jaxems.cli import script_main

    control_map = _script("control_map")
    assert script_main("control_map", control_map.main, ["--gear", "0"]) == 1  # drew gear 12
    assert "--gear: a gear number from 1 to 12 (got 0)" in capsys.readouterr().err


def test_level2_hills_rows_are_level2_and_the_dp_and_the_summary_their_arithmetic(capsys):
    """level2_hills: each row's fuel is Level 2's (`solve_costate`) and the DP's and its
    relaxation's (`reference.ref_dp`) on the route its speeds and grades give; the summary
    counts what the rows say; bad input is one line naming the option."""
    from jaxems.levels import battery as b
    from jaxems.reference import ref_dp

    lh = _script("level2_hills")
    d, _ = main_json(lh, ["--n", "3", "--seed", "7"], capsys)
    rows, vp = d["rows"], load_vehicle().replace(E_b_max=lh.E_MAX)
    assert [r["route"] for r in rows] == [0, 1, 2]
    for r in rows:
        assert all(12.0 <= x <= 22.0 for x in r["speeds_mps"]) and 0.2 <= r["soc0"] <= 0.8
        P_d, v = lh.hill(vp, r["speeds_mps"], r["grades"])
        assert v.shape == (120,)
        w, E0 = np.full(v.shape, lh.W_LEVEL2), r["soc0"] * lh.E_MAX
        c = b.solve_costate(vp, P_d, v, w, None, lh.DT, E_b0=E0)
        assert r["level2_J"] == pytest.approx(float(c.fuel), rel=1e-12)
        assert r["status"] == b.status_names(int(c.status))
        if "dp_J" in r:
            for key, shared in (("dp_J", False), ("relaxed_dp_J", True)):
                want = ref_dp(vp, P_d, v, w, lh.DT, E0, 0.0, lh.E_MAX, n_grid=241,
                              shared=shared)
                assert r[key] == pytest.approx(want, rel=1e-12)
            assert r["relaxed_dp_J"] <= r["dp_J"]
            assert r["excess_pct"] == pytest.approx(100 * (r["level2_J"] / r["dp_J"] - 1))
    solved = [r for r in rows if "dp_J" in r]
    s = d["summary"]
    assert s["solved"] == len(solved) > 0 and (s["routes"], s["battery_MJ"]) == (3, 1.0)
    assert s["above_dp_0.1pct"] == sum(r["excess_pct"] > 0.1 for r in solved)
    assert s["max_excess_pct"] == max(r["excess_pct"] for r in solved)
    assert s["min_over_relaxed_pct"] == min(r["over_relaxed_pct"] for r in solved)
    assert "random hills (seed 7, 1 MJ)" in lh.format_table(d)
    with pytest.raises(SystemExit):
        lh.main(["--n", "0"])
    assert "--n: expected a whole number >= 1" in capsys.readouterr().err
