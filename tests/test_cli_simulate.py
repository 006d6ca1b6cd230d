"""`jaxems simulate`: JSON fields and types, human table, overrides; one-line errors.

The successful runs are in-process (they share the conventional strategy's compilation with
tests/test_experiments.py); the error cases run `python -m jaxems` and fail before compiling.
"""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from jaxems.cli import build_parser, main

ROOT = Path(__file__).resolve().parent.parent

FIELDS = {
    "route": str, "strategy": str, "length_m": float, "trip_time_s": float,
    "level3_trip_time_s": float, "fuel_J": float,
    "fuel_l_per_100km": float, "delta_Eb_J": float, "Eb_min_J": float, "Eb_max_J": float,
    "mode_switches": int, "gear_switches": int, "lambda_b": float,
    "max_speed_shortfall_mps": float, "wall_s": float,
}
LHV_J_PER_KG, DENSITY_KG_PER_L = 42.8e6, 0.832  # data/vehicles/reference_truck.toml [fuel]


def run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_simulate_conventional_json(capsys):
    code, out, err = run(capsys, "simulate", "short_track", "--strategy", "conventional",
                         "--mass", "25000", "--json")
    assert code == 0, err
    assert out.count("\n") == 1  # exactly one JSON object on stdout
    d = json.loads(out)
    for k, typ in FIELDS.items():
        assert isinstance(d[k], typ) and not isinstance(d[k], bool), (k, d[k])
    assert d["route"] == "short_track" and d["strategy"] == "conventional"
    assert d["length_m"] == pytest.approx(1055.0)
    assert d["mass_kg"] == 25000.0 and d["status"] == "ok"
    # the trip at 25 km/h takes 152 s; switches open the driveline and cost a little time
    assert 1055 / (25 / 3.6) <= d["trip_time_s"] <= 1.1 * 1055 / (25 / 3.6) + 1
    assert 1055 / (25 / 3.6) <= d["level3_trip_time_s"] <= d["trip_time_s"]  # Level 3's
    # the conventional truck has no motor: the battery stays where it started (half of 4 MJ)
    assert d["delta_Eb_J"] == 0.0 and d["Eb_min_J"] == d["Eb_max_J"] == 2.0e6
    # the 12 % climbs need lower gears than the flat: the truck shifts
    assert d["gear_switches"] > 0 and d["fuel_J"] > 0
    litres = d["fuel_J"] / LHV_J_PER_KG / DENSITY_KG_PER_L
    assert d["fuel_l_per_100km"] == pytest.approx(litres / (d["length_m"] / 1e5), rel=1e-9)
    assert d["fuel_corrected_J"] == pytest.approx(d["fuel_J"] + d["lambda_b"] * d["delta_Eb_J"])
    assert d["charge_missed"] is False  # no battery, nothing to miss
    assert d["level2_status"] is None  # no Level 2


def test_simulate_battery_override_and_table(capsys):
    code, out, _ = run(capsys, "simulate", "short_track", "--strategy", "conventional",
                       "--battery-MJ", "8", "--json")
    assert code == 0
    d = json.loads(out)
    assert d["battery_MJ"] == 8.0 and d["Eb_min_J"] == pytest.approx(4.0e6)  # half of 8 MJ
    assert d["initial_soc"] == 0.5  # the vehicle file's
    code, out, _ = run(capsys, "simulate", "short_track", "--strategy", "conventional",
                       "--battery-MJ", "8", "--initial-soc", "0.3", "--json")
    d = json.loads(out)
    assert code == 0 and d["initial_soc"] == 0.3
    assert d["Eb_min_J"] == d["Eb_max_J"] == pytest.approx(0.3 * 8e6)  # where it started
    code, out, _ = run(capsys, "simulate", "short_track", "--strategy", "conventional")
    assert code == 0
    lines = out.splitlines()
    assert lines[0].split()[0] == "route" and "short_track" in lines[0]
    col = lines[0].index("short_track")  # values start in one column
    assert all(len(line) > col and line[col - 2:col] == "  " for line in lines)
    assert any(line.startswith("fuel ") and line.endswith("l/100 km") for line in lines)
    assert any(line.startswith("gear switches") for line in lines)
    # the battery balance also in % of the battery (the conventional truck's: none)
    assert any(line.startswith("delta E_b") and line.endswith("MJ (+0.00 % of the battery)")
               for line in lines)


TRACE_HEADER = ["t_s", "s_m", "v_m_s", "v_ref_m_s", "E_b_J", "mode", "gear", "P_d_W", "P_e_W",
                "P_m_W", "P_b_W", "P_f_W", "P_brake_W", "lambda_b", "counted_s", "E_sync_b_J",
                "E_sync_f_J"]


def test_simulate_writes_its_time_series_and_plot(capsys, tmp_path):
    import csv

    import numpy as np

    from jaxems import simulate

    table, png = tmp_path / "run.csv", tmp_path / "run.png"
    code, out, err = run(capsys, "simulate", "short_track", "--strategy", "conventional",
                         "--mass", "25000", "--json", "--csv", str(table), "--plot", str(png))
    assert code == 0, err
    d = json.loads(out)
    with open(table, newline="") as fh:
        rows = list(csv.reader(fh))
    assert rows[0] == TRACE_HEADER
    cols = {k: [r[i] for r in rows[1:]] for i, k in enumerate(TRACE_HEADER)}
    num = {k: np.array(v, float) for k, v in cols.items() if k != "mode"}
    # a row a step of the trip, from the start: steps of 1 s that start before its end
    t = num["t_s"]
    assert t[0] == 0.0 and np.all(np.diff(t) == 1.0)
    assert t[-1] < d["trip_time_s"] <= t[-1] + 1.0
    assert num["s_m"][0] == 0.0 and np.all(np.diff(num["s_m"]) >= 0)
    assert num["s_m"][-1] < d["length_m"]
    # the conventional truck: the engine alone (or the open driveline), the battery untouched
    assert set(cols["mode"]) <= {"Me", "Mo"} and "Me" in cols["mode"]
    assert np.all((num["gear"] >= 1) & (num["gear"] <= 12)) and len(set(cols["gear"])) > 1
    assert np.all(num["E_b_J"] == 2.0e6) and np.all(num["P_b_W"] == 0) and np.all(num["P_m_W"] == 0)
    # the fuel power over the time each step counts and the synchronisation energy the engine
    # supplies at switches are the run's fuel (to the CSV's 10 digits); the short track ends
    # at speed, and its last step counts up to the route's end
    assert np.all(num["counted_s"][:-1] == 1.0) and 0.0 < num["counted_s"][-1] < 1.0
    assert np.sum(num["E_sync_f_J"]) > 0 and np.all(num["E_sync_b_J"] == 0)
    fuel_steps = float(np.sum(num["P_f_W"] * num["counted_s"]) + np.sum(num["E_sync_f_J"]))
    assert fuel_steps == pytest.approx(d["fuel_J"], rel=1e-8)
    # the same columns as the Python API's, to the CSV's 10 digits
    api = simulate("short_track", strategy="conventional", mass_kg=25000.0).trace_columns()
    assert list(api) == TRACE_HEADER
    for k in TRACE_HEADER:
        if k == "mode":
            assert list(api[k]) == cols[k]
        else:
            np.testing.assert_allclose(num[k], api[k], rtol=1e-9, atol=1e-6, err_msg=k)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.csv", "run.png"]  # no temporaries


def test_simulate_checks_its_output_files_before_running(capsys, tmp_path, monkeypatch):
    from jaxems import strategies

    monkeypatch.setattr(strategies, "simulate", lambda *a, **k: pytest.fail("ran before the check"))
    same = str(tmp_path / "run.png")
    for args, words in [
        (("--csv", tmp_path / "missing" / "run.csv"), "--csv: the directory"),
        (("--plot", tmp_path), "--plot: " + str(tmp_path) + " is a directory"),
        (("--csv", ""), "--csv: expected a file name"),  # was "--csv:  is a directory"
        # a PNG under another name; the time series and the plot into one file (the plot
        # overwrote the CSV)
        (("--plot", tmp_path / "run.pdf"), "--plot: the plot is a PNG"),
        (("--csv", same, "--plot", same), "--csv and --plot: the same file"),
    ]:
        code, out, err = run(capsys, "simulate", "short_track", *map(str, args))
        assert code == 1 and out == ""
        assert err.count("\n") == 1 and err.startswith("jaxems: error: ") and words in err
    assert list(tmp_path.iterdir()) == []


def test_simulate_and_compare_never_write_over_their_input(capsys, tmp_path, monkeypatch):
    """`simulate r.csv --csv r.csv` overwrote the route it had read with its time series;
    `compare DIR/conventional.csv --traces DIR` would have; refused before anything runs."""
    from jaxems import strategies

    monkeypatch.setattr(strategies, "simulate", lambda *a, **k: pytest.fail("ran before the check"))
    route = tmp_path / "conventional.csv"
    route.write_text("distance_m,speed_limit_km_h\n0,50\n500,50\n")
    for argv in (["simulate", str(route), "--strategy", "conventional", "--csv", str(route)],
                 ["compare", str(route), "--strategies", "conventional",
                  "--traces", str(tmp_path)]):
        code, out, err = run(capsys, *argv)
        assert code == 1 and out == "" and err.count("\n") == 1
        flag = argv[-2]
        assert f"{flag}: {route} is the route file being read ({route})" in err
    assert route.read_text() == "distance_m,speed_limit_km_h\n0,50\n500,50\n"
    assert [p.name for p in tmp_path.iterdir()] == ["conventional.csv"]


def test_simulate_registered():
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    assert {"route", "predict", "simulate"} <= set(sub.choices)


@pytest.mark.parametrize(
    "args,words",
    [
        (["--strategy", "greedy"], "strategy: unknown 'greedy'"),
        (["--mass", "-5"], "mass_kg: must be from 1000 to 200000 kg"),
        (["--battery-MJ", "0"], "battery_MJ: must be > 0"),
        (["--initial-soc", "1.5"], "initial_soc: must be in [0, 1]"),
        (["--n-iter", "0"], "--n-iter: must be a whole number >= 1"),
        (["--option", "bogus=1"], "--option: unknown option 'bogus'"),
        (["--option", "l2_pieces"], "--option 'l2_pieces': expected NAME=VALUE"),
        (["--option", "n_iter=0"], "n_iter: must be a whole number >= 1"),
        # "Invalid value (at line 1, column 5)", the column counting an internal "v = "; the
        # part after a newline was parsed as TOML and dropped
        (["--option", "n_iter=abc"], "--option n_iter: not a valid value ('abc'; one TOML "
                                     "value on one line"),
        (["--option", "plant_extra=0.2\nend_cap=false"],
         "--option plant_extra: not a valid value ('0.2\\nend_cap=false';"),
        (["--option", "n_iter=2", "--n-iter", "3"], "--n-iter: given twice"),
        (["--option", "dwell=2", "--option", "dwell=4"], "dwell given twice"),  # kept the last
        # an option the strategy ignores would change nothing
        (["--strategy", "baseline", "--option", "h1=3"],
         "--option: h1: not an option of baseline, which would ignore it"),
        (["--strategy", "baseline", "--n-iter", "3"], "n_iter: not an option of baseline"),
    ],
)
def test_simulate_bad_options_in_process(capsys, args, words):
    code, out, err = run(capsys, "simulate", "short_track", *args)
    assert code == 1 and out == ""
    assert err.count("\n") == 1 and err.startswith("jaxems: error: ") and words in err


@pytest.mark.parametrize(
    "args,words",
    [
        (["short_track", "--strategy", "greedy"], "unknown 'greedy'"),
        (["short_track", "--mass", "-5"], "mass_kg: must be from 1000 to 200000 kg"),
        (["short_track", "--battery-MJ", "0"], "battery_MJ: must be > 0"),
        (["no_such_dir/no_such_route.vdri"], "no such file"),
    ],
)
def test_simulate_errors_python_dash_m(args, words):
    r = subprocess.run([sys.executable, "-m", "jaxems", "simulate", *args], capture_output=True,
                       text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 1 and r.stdout == ""
    assert r.stderr.count("\n") == 1 and r.stderr.startswith("jaxems: error: ")
    assert words in r.stderr and "Traceback" not in r.stderr


class _FakeRun:
    """What `strategies.simulate` returns, as far as the CLI reads it."""

    def __init__(self, delta_Eb_J, status="ok", level2=-1, strategy="baseline", fuel_J=7e6,
                 lambda_b=-2.0):
        self.strategy = strategy
        self.fields = {"length_m": 1055.0, "trip_time_s": 153.0, "level3_trip_time_s": 151.9,
                       "fuel_J": fuel_J, "fuel_l_per_100km": 18.6, "fuel_corrected_J": fuel_J,
                       "delta_Eb_J": delta_Eb_J, "Eb_min_J": 1e6, "Eb_max_J": 3e6,
                       "mode_switches": 4, "gear_switches": 7, "lambda_b": lambda_b,
                       "max_speed_shortfall_mps": 0.5, "status": status,
                       "level2_status": level2, "wall_s": 0.1}

    def as_dict(self):
        return {"route": "short_track", "strategy": self.strategy, **self.fields}


@pytest.mark.parametrize("delta, status, missed", [
    (-0.101e6, "ok", True),  # 2.5 % of the 4 MJ battery
    (0.039e6, "ok", False),  # within 1 %
    (0.041e6, "ok", True),
    (-1.0e6, "unfinished", False),  # an unfinished run's balance is no charge verdict
    (-1.0e6, "infeasible-route", False),
])
def test_simulate_flags_a_charge_miss_as_sweep_reports_do(capsys, monkeypatch, delta, status,
                                                          missed):
    """`charge_missed`: |delta_Eb_J| beyond 1 % of the battery on a finished run (the check
    `report.off_charge` applies to sweeps), in the JSON and on the table's delta E_b line."""
    from jaxems import strategies

    monkeypatch.setattr(strategies, "simulate", lambda *a, **k: _FakeRun(delta, status))
    code, out, err = run(capsys, "simulate", "short_track", "--strategy", "baseline", "--json")
    assert code == 0, err
    assert json.loads(out)["charge_missed"] is missed
    code, out, _ = run(capsys, "simulate", "short_track", "--strategy", "baseline")
    line = next(x for x in out.splitlines() if x.startswith("delta E_b"))
    assert line.endswith("beyond 1 %: not charge sustaining") is missed
    # an unfinished run, or one on a route the truck cannot climb, has no trip time to set
    # against Level 3's (it printed 0.0 s, -100 %)
    trip = next(x for x in out.splitlines() if x.startswith("trip time"))
    assert ("did not reach the route's end" in trip) is (status == "unfinished")
    assert ("an infeasible route: the truck cannot climb it" in trip) is (
        status == "infeasible-route")
    assert ("Level 3: 151.9 s" in trip) is (status == "ok")
    assert trip.split()[2] == ("153.0" if status == "ok" else "-")


def test_simulate_passes_options_on_and_echoes_them(capsys, monkeypatch):
    """`--option NAME=VALUE` (repeatable, TOML values) reaches `simulate` as keyword options,
    with `--n-iter`; the JSON and the table echo them."""
    from jaxems import strategies

    seen = {}

    def fake(*a, **k):
        seen.update(k)
        return _FakeRun(0.0)

    monkeypatch.setattr(strategies, "simulate", fake)
    code, out, err = run(capsys, "simulate", "short_track", "--strategy", "multilevel",
                         "--option", "sustain=false", "--option", "l2_pieces = 64",
                         "--n-iter", "3", "--json")
    assert code == 0, err
    opts = {"sustain": False, "l2_pieces": 64, "n_iter": 3}
    assert {k: seen[k] for k in opts} == opts
    assert json.loads(out)["options"] == opts
    code, out, _ = run(capsys, "simulate", "short_track", "--option", "tau_E=30.5")
    assert code == 0 and seen["tau_E"] == 30.5
    assert any(line.startswith("options") and line.endswith("tau_E=30.5")
               for line in out.splitlines())


def test_simulate_names_the_last_plans_level2_flags(capsys, monkeypatch):
    """multilevel's (and multilevel-eco's) last plan's Level 2 flags (`level2_status`), by
    name, in the JSON and the table, with a hint where its pieces ran out; null for a strategy
    without the iteration's Level 2."""
    from jaxems import strategies
    from jaxems.levels import battery as l2

    for code, names in ((l2.AT_GUARD | l2.PIECES_EXHAUSTED, ["at-guard", "pieces-exhausted"]),
                        (0, [])):
        monkeypatch.setattr(strategies, "simulate", lambda *a, c=code, **k: _FakeRun(0.0, level2=c))
        code_, out, _ = run(capsys, "simulate", "short_track", "--json")
        assert code_ == 0 and json.loads(out)["level2_status"] == names
        code_, out, _ = run(capsys, "simulate", "short_track")
        line = next(x for x in out.splitlines() if x.startswith("Level 2 (last plan)"))
        assert line.endswith("at-guard, pieces-exhausted (more pieces: --option l2_pieces=N)"
                             if names else "converged")
    monkeypatch.setattr(strategies, "simulate", lambda *a, **k: _FakeRun(0.0))
    code_, out, _ = run(capsys, "simulate", "short_track", "--strategy", "baseline", "--json")
    assert code_ == 0 and json.loads(out)["level2_status"] is None
    code_, out, _ = run(capsys, "simulate", "short_track", "--strategy", "baseline")
    assert not any(x.startswith("Level 2") for x in out.splitlines())


def test_simulate_gives_the_eco_optimisations_figures(capsys, monkeypatch):
    """multilevel-eco's price of time, Level 3's own trip time and the optimiser's flags by
    name, in the JSON and the table (an eco-trip-time-missed could not be sized from the
    output before); absent for the other strategies."""
    from types import SimpleNamespace

    from jaxems import strategies
    from jaxems.levels import velocity as vel

    def fake(*a, **k):
        r = _FakeRun(0.0, status="eco-trip-time-missed", strategy="multilevel-eco")
        r.extra = SimpleNamespace(lambda_t=3693.2, level3_trip_time=151.9,
                                  eco_status=vel.ECO_TARGET_MISSED)
        return r

    monkeypatch.setattr(strategies, "simulate", fake)
    code, out, err = run(capsys, "simulate", "short_track", "--strategy", "multilevel-eco",
                         "--json")
    assert code == 0, err
    d = json.loads(out)
    assert (d["eco_lambda_t"], d["eco_level3_trip_time_s"], d["eco_status"]) == (
        3693.2, 151.9, ["target-missed"])
    code, out, _ = run(capsys, "simulate", "short_track", "--strategy", "multilevel-eco")
    assert any(x.startswith("eco-driving") and x.endswith(
        "lambda_t 3693 J/s, Level 3's own trip 151.9 s, target-missed")
        for x in out.splitlines())
    monkeypatch.setattr(strategies, "simulate", lambda *a, **k: _FakeRun(0.0))
    code, out, _ = run(capsys, "simulate", "short_track", "--strategy", "baseline", "--json")
    assert "eco_lambda_t" not in json.loads(out)


# ---------------------------------------------------------------------------------- compare
FAKE = {"conventional": (13.0e6, 0.0, 0.0), "baseline": (11.0e6, -2.2, -0.101e6),
        "multilevel": (7.0e6, -2.0, 0.02e6)}


def _fake_simulate(seen, status=None):
    def fake(route, vp, strategy, **k):
        seen.append((strategy, k))
        fuel, lam, delta = FAKE[strategy]
        return _FakeRun(delta, (status or {}).get(strategy, "ok"), strategy=strategy,
                        fuel_J=fuel, lambda_b=lam)
    return fake


def test_compare_strategies_corrects_and_saves_as_sweeps_do(monkeypatch):
    """`compare_strategies`: one row per strategy in the order given; corrected fuel J +
    lambda_b dE_b (none for the conventional truck), savings 100 (F_ref - F) / F_ref on it
    against conventional and baseline (None where the reference did not run or did not
    finish), the 1 % charge check; options reach every run; progress sees each row."""
    import jaxems
    from jaxems import strategies

    compare_strategies = jaxems.compare_strategies  # the package's name for it
    seen, done = [], []
    monkeypatch.setattr(strategies, "simulate", _fake_simulate(seen))
    rows = compare_strategies("short_track", "reference_truck", ["multilevel", "conventional",
                              "baseline"], battery_MJ=4.0, n_iter=3, progress=done.append)
    assert [r["strategy"] for r in rows] == ["multilevel", "conventional", "baseline"]
    assert [r["strategy"] for r in done] == ["multilevel", "conventional", "baseline"]
    assert all(k["options"].n_iter == 3 for _, k in seen)
    F = {s: f + lam * d for s, (f, lam, d) in FAKE.items()}  # plain: J + lambda_b dE_b
    by = {r["strategy"]: r for r in rows}
    for s, r in by.items():
        assert r["fuel_corrected_J"] == pytest.approx(F[s], rel=1e-12)
        assert r["saving_vs_conventional_pct"] == pytest.approx(
            100 * (F["conventional"] - F[s]) / F["conventional"], rel=1e-12)
        assert r["saving_vs_baseline_pct"] == pytest.approx(
            100 * (F["baseline"] - F[s]) / F["baseline"], rel=1e-12)
        assert r["fuel_corrected_l_per_100km"] == pytest.approx(
            r["fuel_l_per_100km"] * F[s] / FAKE[s][0], rel=1e-12)
    # |dE_b| against 1 % of the 4 MJ battery: 0.101 MJ misses, 0.02 MJ and 0 do not
    assert [by[s]["charge_missed"] for s in FAKE] == [False, True, False]
    # the order of the strategies changes the rows' order, nothing in them
    again = compare_strategies("short_track", "reference_truck", ["baseline", "conventional",
                               "multilevel"], battery_MJ=4.0, n_iter=3)
    assert {r["strategy"]: r for r in again} == by

    seen.clear()
    monkeypatch.setattr(strategies, "simulate",
                        _fake_simulate(seen, status={"conventional": "unfinished"}))
    rows = compare_strategies("short_track", strategies=["conventional", "multilevel"])
    assert all(r["saving_vs_conventional_pct"] is None for r in rows)  # its reference unfinished
    assert all(r["saving_vs_baseline_pct"] is None for r in rows)  # not run
    assert rows[0]["charge_missed"] is False  # an unfinished run is no charge verdict


@pytest.mark.parametrize("strategies, kw, words", [
    (["conventional", "greedy"], {}, "unknown 'greedy'"),
    (["baseline", "baseline"], {}, "each at most once"),
    ([], {}, "none given"),
    (["baseline"], {"n_iterations": 2}, "n_iterations"),
    (["baseline"], {"mass_kg": -1.0}, "mass_kg"),
])
def test_compare_strategies_checks_before_running(monkeypatch, strategies, kw, words):
    from jaxems import strategies as S
    from jaxems.sweep import compare_strategies

    monkeypatch.setattr(S, "simulate", lambda *a, **k: pytest.fail("ran before the check"))
    with pytest.raises(ValueError, match=words):
        compare_strategies("short_track", strategies=strategies, **kw)


def test_compare_cli_json_and_table(capsys):
    """`jaxems compare`: one JSON object with the vehicle and a row per strategy; the table has
    a line per strategy and '-' where a saving's reference was not run. (The conventional
    truck only: its compilation is shared with the simulate tests above.)"""
    code, out, err = run(capsys, "compare", "short_track", "--strategies", "conventional",
                         "--mass", "25000", "--json")
    assert code == 0, err
    assert out.count("\n") == 1
    d = json.loads(out)
    assert (d["route"], d["mass_kg"], d["battery_MJ"]) == ("short_track", 25000.0, 4.0)
    (row,) = d["rows"]
    assert row["strategy"] == "conventional" and row["status"] == "ok"
    assert row["saving_vs_conventional_pct"] == 0.0 and row["saving_vs_baseline_pct"] is None
    assert row["fuel_corrected_J"] == row["fuel_J"] and row["charge_missed"] is False
    assert row["level2_status"] is None  # as simulate --json: names, None without a Level 2
    code, out, err = run(capsys, "compare", "short_track", "--strategies", "conventional",
                         "--mass", "25000")
    assert code == 0 and "conventional" in err  # progress on stderr
    line = next(x for x in out.splitlines() if x.startswith("conventional"))
    cells = line.split()
    assert cells[1] == f"{row['fuel_J'] / 1e6:.3f}" and "-" in cells and cells[-1] == "ok"


def test_compare_shows_no_trip_time_where_simulate_shows_none(capsys, monkeypatch):
    """On a route Level 3 predicts the truck cannot climb, and in an unfinished run, the trip
    time is '-' in `compare`'s table as in `simulate`'s, with simulate's words once under it
    (a baseline that crawled up such a route with its motor's help showed its trip, 97.9 s);
    savings against a run that is not ok are '-' too."""
    from jaxems import strategies
    from jaxems.cli import NO_TRIP_TIME

    status = {"conventional": "infeasible-route+unfinished", "baseline": "infeasible-route"}
    monkeypatch.setattr(strategies, "simulate", _fake_simulate([], status=status))
    code, out, err = run(capsys, "compare", "short_track")
    assert code == 0, err
    lines = out.splitlines()
    head = next(x for x in lines if x.startswith("strategy"))
    trip = slice(head.index("   trip s"), head.index("   trip s") + len("   trip s"))
    saving = slice(head.index(" vs conv. %"), head.index(" vs base. %") + len(" vs base. %"))
    for s in FAKE:
        row = next(x for x in lines if x.startswith(s))
        assert row[trip].strip() == ("153.0" if s == "multilevel" else "-"), row
        assert row[saving].split() == ["-", "-"], row  # both references are not ok
    assert [x for x in lines if x.startswith("- trip s: ")] == [
        f"- trip s: {NO_TRIP_TIME['infeasible-route']}"]
    # simulate's table says the same of the same run
    monkeypatch.setattr(strategies, "simulate", lambda *a, **k: _FakeRun(0.0, status["baseline"]))
    code, out, _ = run(capsys, "simulate", "short_track", "--strategy", "baseline")
    line = next(x for x in out.splitlines() if x.startswith("trip time"))
    assert line.split(None, 2)[2] == f"- ({NO_TRIP_TIME['infeasible-route']})"


def test_compare_writes_each_runs_traces(capsys, tmp_path, monkeypatch):
    """`compare --traces DIR` makes DIR and writes each strategy's time series and traces there,
    as `simulate --csv / --plot` write them; a DIR that cannot be made is one line before any
    run."""
    import csv

    out_dir = tmp_path / "traces"
    code, out, err = run(capsys, "compare", "short_track", "--strategies", "conventional",
                         "--mass", "25000", "--json", "--traces", str(out_dir))
    assert code == 0, err
    (row,) = json.loads(out)["rows"]
    assert sorted(p.name for p in out_dir.iterdir()) == ["conventional.csv", "conventional.png"]
    with open(out_dir / "conventional.csv", newline="") as fh:
        rows = list(csv.reader(fh))
    assert rows[0] == TRACE_HEADER
    t = [float(r[0]) for r in rows[1:]]
    assert t[0] == 0.0 and t[-1] < row["trip_time_s"] <= t[-1] + 1.0  # the run's whole trip
    assert (out_dir / "conventional.png").read_bytes()[:4] == b"\x89PNG"
    from jaxems import strategies

    monkeypatch.setattr(strategies, "simulate", lambda *a, **k: pytest.fail("ran before the check"))
    for target, words, more in [(tmp_path / "no" / "dir", "--traces: the directory", []),
                                (out_dir / "conventional.csv", "is not a directory", []),
                                (tmp_path / "new", "unknown 'bogus'", ["--strategies", "bogus"])]:
        code, out, err = run(capsys, "compare", "short_track", "--traces", str(target), *more)
        assert code == 1 and out == "" and err.count("\n") == 1 and words in err
    assert not (tmp_path / "new").exists()  # made only once the runs start


def test_compare_cli_errors(capsys):
    code, _, err = run(capsys, "compare", "short_track", "--strategies", "conventional,greedy")
    assert code == 1 and "unknown 'greedy'" in err
    code, _, err = run(capsys, "compare", "no_such_route", "--strategies", "conventional")
    assert code == 1 and "no_such_route" in err
    code, _, err = run(capsys, "compare", "short_track", "--option", "bogus=1")
    assert code == 1 and "bogus" in err
    code, _, err = run(capsys, "compare", "short_track", "--option", "dp_n_E=51")
    assert code == 1 and ("--option: dp_n_E: not an option of conventional, baseline or "
                          "multilevel, which would ignore it (an option of dp-bound)") in err
