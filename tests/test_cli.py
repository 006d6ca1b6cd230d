"""Command line: route and predict subcommands, JSON output, one-line errors; the experiment."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from jaxems.cli import CLIError, build_parser, check_not_inputs, main
from jaxems.params import load_vehicle
from jaxems.reference import road_load

ROOT = Path(__file__).resolve().parent.parent


def run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_route_json(capsys):
    code, out, err = run(capsys, "route", "short_track", "--json")
    assert code == 0 and err == ""
    d = json.loads(out)
    assert d["route"] == "short_track" and d["length_m"] == 1055.0
    assert d["duration_s"] == pytest.approx(1055 / (25 / 3.6), rel=1e-9)
    assert d["gradient_min_pct"] == pytest.approx(-12)
    assert d["gradient_max_pct"] == pytest.approx(12)
    assert d["stops"] == 0 and d["stop_time_s"] == 0


def test_route_text_and_vdri_file(capsys):
    path = ROOT / "data/routes/vecto-3.0.1/RegionalDelivery.vdri"
    code, out, _ = run(capsys, "route", str(path))
    assert code == 0
    # what the file says, read as plain CSV: <s>,<v>,<grad>,<stop>
    rows = [line.split(",") for line in path.read_text().splitlines()[1:] if line.strip()]
    stops = [float(r[3]) for r in rows if float(r[3]) > 0]
    assert f"{float(rows[-1][0]) / 1000:.3f} km" in out
    assert f"{len(stops)} ({sum(stops):.0f} s standing)" in out


def test_predict_json_mass_and_csv(capsys, tmp_path):
    code, out, _ = run(capsys, "predict", "short_track", "--mass", "25000", "--json")
    assert code == 0
    d = json.loads(out)
    assert d["mass_kg"] == 25000.0 and d["feasible"] is True
    # the steepest climb (12 %) at the track's constant 25 km/h: the road load's power there
    v = 25 / 3.6
    vp = load_vehicle("reference_truck").replace(mass=25000.0)
    assert d["P_d_max_kW"] == pytest.approx(road_load(vp, v, 0.12) * v / 1e3, rel=1e-6)
    heavier = json.loads(run(capsys, "predict", "short_track", "--mass", "40000", "--json")[1])
    assert heavier["energy_traction_MJ"] > d["energy_traction_MJ"]
    csv = tmp_path / "ts.csv"
    code, out, _ = run(capsys, "predict", "short_track", "--csv", str(csv))
    assert code == 0 and "trip time" in out
    lines = csv.read_text().splitlines()
    assert lines[0] == "t_s,s_m,v_m_s,a_m_s2,grade,P_d_W" and len(lines) == 1 + 152


def test_predict_checks_dt_and_writes_its_csv_whole(capsys, tmp_path, monkeypatch):
    csv = tmp_path / "ts.csv"
    for dt in ("100", "0.001"):
        code, _, err = run(capsys, "predict", "short_track", "--dt", dt, "--csv", str(csv))
        assert code == 1 and "dt: must be a time step from 0.05 to 10 s" in err
    with pytest.raises(SystemExit) as e:  # not a finite number: the command line's error
        run(capsys, "predict", "short_track", "--dt", "nan", "--csv", str(csv))
    assert e.value.code == 2 and "argument --dt: expected a finite number (got nan)" in (
        capsys.readouterr().err)
    assert not csv.exists()
    # interrupted while writing: no file, no temporary left beside it
    import jaxems.sweep as sw

    def interrupted(fd):
        raise KeyboardInterrupt

    monkeypatch.setattr(sw.os, "fsync", interrupted)
    code, _, err = run(capsys, "predict", "short_track", "--csv", str(csv))
    assert code == 130 and err == "jaxems: interrupted\n"
    assert list(tmp_path.iterdir()) == []


def test_interrupted_sweep_says_how_to_go_on(capsys, monkeypatch, tmp_path):
    import jaxems.sweep as sw

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(sw, "run_sweep", interrupted)
    monkeypatch.setattr(sw, "_in_process_devices", lambda n: None)  # this process's devices
    code, _, err = run(capsys, "sweep", str(tmp_path / "x.toml"))
    assert code == 130 and "interrupted; finished chunks are kept" in err and "--resume" in err


@pytest.mark.parametrize("status", [0, 1, 130])
def test_the_process_ends_at_once_after_ctrl_c(monkeypatch, status):
    """The script's entry: main's status as the process's; after Ctrl-C os._exit (no teardown
    of the interpreter under XLA's compiler threads, which crashed with status 139 when a
    compilation was interrupted), once the streams are flushed; otherwise sys.exit."""
    import jaxems.cli as cli

    calls = []
    monkeypatch.setattr(cli, "main", lambda: status)
    monkeypatch.setattr(cli.os, "_exit", lambda code: calls.append(("_exit", code)))
    monkeypatch.setattr(cli.sys.stderr, "flush", lambda: calls.append(("flush",)))
    with pytest.raises(SystemExit) as e:
        cli.run()
    assert e.value.code == status  # after the stub _exit returns, sys.exit follows
    assert calls == ([("flush",), ("_exit", 130)] if status == 130 else [])


def test_sweep_devices_are_capped(capsys, tmp_path):
    """--devices 1000 flooded stderr with XLA's rendezvous warnings and aborted after 70 s;
    refused before JAX starts (`sweep.DEVICES_MAX`)."""
    from jaxems import shard

    started = shard.backends_started()
    code, out, err = run(capsys, "sweep", str(tmp_path / "x.toml"), "--devices", "100000")
    assert code == 1 and out == "" and err.count("\n") == 1
    assert err.startswith("jaxems: error: --devices: at most ") and "(got 100000;" in err
    assert shard.backends_started() == started  # nothing started


def test_output_paths_name_the_flag(tmp_path):
    """A file where a directory should be, and an empty path (the current directory), were
    "the directory afile does not exist" and "--csv:  is a directory"."""
    from jaxems.cli import CLIError, check_output

    afile = tmp_path / "afile"
    afile.write_text("")
    for path, flag, directory, words in [
        (afile / "x.csv", "--csv", False, f"--csv: {afile} is not a directory"),
        (afile / "sub" / "x.csv", "--plot", False, f"--plot: {afile} is not a directory"),
        (afile / "traces", "--traces", True, f"--traces: {afile} is not a directory"),
        ("", "--csv", False, "--csv: expected a file name (got '')"),
        ("", "--traces", True, "--traces: expected a directory name (got '')"),
        (tmp_path / "no" / "x.csv", "--csv", False, "--csv: the directory"),
    ]:
        with pytest.raises(CLIError) as e:
            check_output(str(path), flag, directory)
        assert str(e.value).startswith(words), e.value
    assert check_output(str(tmp_path / "x.csv"), "--csv") == tmp_path / "x.csv"


def test_an_output_never_overwrites_an_input(capsys, tmp_path, monkeypatch):
    """`predict r.csv --csv r.csv` (and --csv naming the vehicle file) wrote the time series
    over the file it had read and exited 0; refused before anything runs, naming both."""
    from jaxems.levels import velocity

    monkeypatch.setattr(velocity, "predict_velocity", lambda *a, **k: pytest.fail("ran"))
    route = tmp_path / "r.csv"
    route.write_text("distance_m,speed_limit_km_h\n0,50\n500,50\n")
    vehicle = tmp_path / "v.toml"
    vehicle.write_text((ROOT / "data/vehicles/reference_truck.toml").read_text())
    (tmp_path / "link.csv").symlink_to(route)
    before = {p.name: p.read_bytes() for p in (route, vehicle)}
    for csv, what, src in [(route, "route", route), (tmp_path / "link.csv", "route", route),
                           (tmp_path / "sub" / ".." / "r.csv", "route", route),
                           (vehicle, "vehicle", vehicle)]:
        (tmp_path / "sub").mkdir(exist_ok=True)
        code, out, err = run(capsys, "predict", str(route), "--vehicle", str(vehicle),
                             "--csv", str(csv))
        assert code == 1 and out == "" and err.count("\n") == 1
        assert f"--csv: {csv} is the {what} file being read ({src})" in err
    assert {p.name: p.read_bytes() for p in (route, vehicle)} == before
    # the bundled vehicle, by name
    bundled = ROOT / "data/vehicles/reference_truck.toml"
    with pytest.raises(CLIError, match="is the vehicle file being read"):
        check_not_inputs([("--csv", bundled)], str(route), "reference_truck")
    check_not_inputs([("--csv", tmp_path / "new.csv"), ("--plot", None)], str(route), "x")


def test_scripts_end_bad_input_in_one_line(capsys):
    # the experiments' and benchmarks' entry (`script_main`) and argument types
    import argparse

    from jaxems.cli import positive_float, positive_int, script_main

    def bad():
        raise ValueError("route x: no such\n  route")

    assert script_main("exp", bad) == 1
    assert capsys.readouterr().err == "exp: error: route x: no such route\n"
    assert script_main("exp", lambda n: n, 0) == 0 and script_main("exp", lambda: 3) == 3
    # a run that does not fit in memory: one line with what shrinks it, not XLA's traceback
    import jax

    def too_big():
        raise jax.errors.JaxRuntimeError("RESOURCE_EXHAUSTED: Out of memory allocating "
                                         "9250356819376 bytes.\nmore of XLA's text")

    assert script_main("exp", too_big) == 1
    err = capsys.readouterr().err
    assert err.startswith("exp: error: out of memory; a shorter route") and err.count("\n") == 1
    assert "(RESOURCE_EXHAUSTED: Out of memory allocating 9250356819376 bytes.)" in err

    def other():
        raise RuntimeError("not memory")

    with pytest.raises(RuntimeError, match="not memory"):  # any other error stays an error
        script_main("exp", other)
    for f, text in ((positive_int, "0"), (positive_int, "1.5"), (positive_float, "-5"),
                    (positive_float, "nan"), (positive_float, "x"), (positive_int, "1_0"),
                    (positive_float, "2_5"), (positive_float, "\uff12")):
        with pytest.raises(argparse.ArgumentTypeError, match="expected a"):
            f(text)
    assert positive_int("3") == 3 and positive_float("2.5") == 2.5


@pytest.mark.parametrize("argv, words", [
    (["simulate", "short_track", "--mass", "20_000"], "argument --mass: expected a finite number "
                                                      "in ASCII digits, as route files write"),
    (["simulate", "short_track", "--mass", "\uff12\uff10\uff10\uff10\uff10"],
     "argument --mass: expected a finite number in ASCII digits"),  # full-width digits
    (["compare", "short_track", "--battery-MJ", "nan"], "argument --battery-MJ: expected a "
                                                        "finite number (got nan)"),
    (["simulate", "short_track", "--initial-soc", "inf"], "argument --initial-soc: expected"),
    (["route", "short_track", "--ds", "1_0"], "argument --ds: expected a finite number"),
    (["simulate", "short_track", "--n-iter", "1_0"], "argument --n-iter: expected a whole number"),
    (["simulate", "short_track", "--n-iter", "2.5"], "argument --n-iter: expected a whole number "
                                                     "(got '2.5')"),
    (["sweep", "x.toml", "--workers", "1_6"], "argument --workers: expected a whole number"),
    (["sweep", "x.toml", "--devices", "\u0664"], "argument --devices: expected a whole number"),
])
def test_command_line_numbers_are_read_as_route_files_read_them(capsys, argv, words):
    """A number on the command line is one as a route file's cell is (`io._table._NUMBER`):
    float() and int() alone took 20_000, full-width or Arabic-Indic digits as numbers, and nan
    or inf, which failed later under an internal name (mass_kg: ...). A malformed
    command line: argparse's error, naming the option, status 2."""
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 2
    assert words in capsys.readouterr().err
    args = build_parser().parse_args(["simulate", "short_track", "--mass", "2e4", "--dt", ".5",
                                      "--n-iter", "+3", "--initial-soc", "0.25"])
    assert (args.mass, args.dt, args.n_iter, args.initial_soc) == (20000.0, 0.5, 3, 0.25)


def test_predict_vehicle_file(capsys, tmp_path):
    toml = (ROOT / "data/vehicles/reference_truck.toml").read_text()
    p = tmp_path / "light.toml"
    p.write_text(toml.replace("mass_kg = 20000.0", "mass_kg = 12000.0"))
    d = json.loads(run(capsys, "predict", "short_track", "--vehicle", str(p), "--json")[1])
    assert d["mass_kg"] == 12000.0


@pytest.mark.parametrize(
    "argv,words",
    [
        (["route", "{tmp}/bad.vdri"], "line 3, column <v>: not a number"),
        (["predict", "{tmp}/missing.vdri"], "no such file"),
        (["predict", "no_such_route"], "no such route file"),
        (["predict", "short_track", "--mass", "-5"], "mass_kg: must be from 1000 to 200000 kg"),
        (["predict", "short_track", "--vehicle", "nope"], "no such vehicle file"),
        (["predict", "short_track", "--vehicle", "{tmp}/v.toml"], "vehicle.mass_kg: missing"),
        (["route", "{tmp}/empty.csv"], "empty file"),
    ],
)
def test_errors_are_one_line(capsys, tmp_path, argv, words):
    (tmp_path / "bad.vdri").write_text("<s>,<v>,<grad>,<stop>\n0,50,0,0\n100,x,0,0\n")
    (tmp_path / "empty.csv").write_text("")
    (tmp_path / "v.toml").write_text("[vehicle]\nair_density_kg_m3 = 1.2\n")
    code, out, err = run(capsys, *[a.replace("{tmp}", str(tmp_path)) for a in argv])
    assert code != 0 and out == ""
    assert err.count("\n") == 1 and err.startswith("jaxems: error: ")
    assert words in err
    assert "Traceback" not in err


def test_usage_errors_exit_2(capsys):
    with pytest.raises(SystemExit) as e:
        main([])
    assert e.value.code == 2
    with pytest.raises(SystemExit) as e:
        main(["predict"])
    assert e.value.code == 2
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    assert {"route", "predict"} <= set(sub.choices)


def test_python_dash_m_and_experiment():
    r = subprocess.run(
        [sys.executable, "-m", "jaxems", "route", "short_track", "--json"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=120,
    )
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["length_m"] == 1055.0
    r = subprocess.run(
        [sys.executable, "experiments/level3_short_track.py", "--json"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=120,
    )
    assert r.returncode == 0, r.stderr
    seg = json.loads(r.stdout)["segments"]
    assert [s["slope_pct"] for s in seg] == [6, -12, 12, -6]
    for s, paper in zip(seg, (113, -192, 215, -90), strict=True):
        assert abs(s["P_d_kW"] - paper) <= 0.05 * abs(paper)


def test_demo_runs(tmp_path, capsys):
    """The demo's Level 3 part: one row and one plot a bundled route, each row the route's
    length (read as plain CSV from its file), stops and a feasible prediction."""
    from jaxems import demo
    from jaxems.io import list_routes, route_name

    assert demo.main(["--out", str(tmp_path), "--level3-only"]) == 0
    pngs = sorted(p.name for p in tmp_path.glob("*.png"))
    assert "level3_short_track.png" in pngs and len(pngs) == 4
    rows = {ln.split()[0]: ln.split() for ln in capsys.readouterr().out.splitlines()
            if ln.split() and ln.split()[0] in {route_name(p) for p in list_routes()}}
    assert len(rows) == 4
    for path in list_routes():
        lines = [ln for ln in path.read_text().splitlines() if ln.strip()]
        cells = [ln.split(",") for ln in lines if not ln.startswith(("#", "<", "distance"))]
        row = rows[route_name(path)]
        assert float(row[1]) == pytest.approx(float(cells[-1][0]) / 1000, abs=0.005), row
        stops = sum(1 for c in cells if float(c[3]) > 0)
        assert int(row[5]) == stops and row[-1] == "yes", row


def test_cache_dir_from_the_environment(monkeypatch, tmp_path):
    """Where the commands keep JAX's compilation cache: $JAXEMS_CACHE_DIR (empty: none), else
    $XDG_CACHE_HOME/jaxems/jax, else ~/.cache/jaxems/jax."""
    from jaxems import cli

    monkeypatch.setenv("JAXEMS_CACHE_DIR", str(tmp_path / "c"))
    assert cli.cache_dir() == tmp_path / "c"
    monkeypatch.setenv("JAXEMS_CACHE_DIR", "")
    assert cli.cache_dir() is None
    monkeypatch.delenv("JAXEMS_CACHE_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert cli.cache_dir() == tmp_path / "xdg" / "jaxems" / "jax"
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert cli.cache_dir() == tmp_path / "home" / ".cache" / "jaxems" / "jax"


def test_commands_use_a_compilation_cache_unless_jax_has_one(monkeypatch, tmp_path):
    """The commands' setup turns JAX's persistent cache on in `cache_dir()` (made if missing)
    where JAX has none, and keeps one JAX has (the suite's, JAX_COMPILATION_CACHE_DIR); a
    directory that cannot be made, or an empty JAXEMS_CACHE_DIR, leaves it off."""
    import jax

    from jaxems import cli

    own = jax.config.jax_compilation_cache_dir
    assert own  # the suite's (tests/conftest.py)
    monkeypatch.setenv("JAXEMS_CACHE_DIR", str(tmp_path / "a" / "b"))
    try:
        cli._setup_jax()
        assert jax.config.jax_compilation_cache_dir == own  # JAX's own kept
        jax.config.update("jax_compilation_cache_dir", None)
        cli._setup_jax()
        assert jax.config.jax_compilation_cache_dir == str(tmp_path / "a" / "b")
        assert (tmp_path / "a" / "b").is_dir()
        jax.config.update("jax_compilation_cache_dir", None)
        (tmp_path / "file").write_text("")
        monkeypatch.setenv("JAXEMS_CACHE_DIR", str(tmp_path / "file" / "sub"))
        cli._setup_jax()
        assert jax.config.jax_compilation_cache_dir is None
        monkeypatch.setenv("JAXEMS_CACHE_DIR", "")
        cli._setup_jax()
        assert jax.config.jax_compilation_cache_dir is None
    finally:
        jax.config.update("jax_compilation_cache_dir", own)


@pytest.mark.parametrize("workers, called", [(None, True), (2, False)])
def test_an_in_process_sweep_uses_the_compilation_cache(monkeypatch, workers, called):
    """`jaxems sweep` in this process turns the commands' compilation cache on; a local
    cluster's workers share the results directory's instead (`sweep._executor`)."""
    import argparse

    from jaxems import cli, sweep

    calls = []
    monkeypatch.setattr(cli, "use_compilation_cache", lambda: calls.append(1))
    monkeypatch.setattr(sweep, "_in_process_devices", lambda n: None)

    class Summary:
        def text(self):
            return "done"

    monkeypatch.setattr(sweep, "run_sweep", lambda *a, **k: Summary())
    args = argparse.Namespace(workers=workers, scheduler=None, devices=None, sweep_file="x.toml",
                              out=None, resume=False, quiet=True, no_report=True)
    assert sweep.cmd_sweep(args) == 0
    assert bool(calls) is called


def test_a_missing_or_not_finite_number_prints_as_a_dash():
    """Tables print '-' where a value is missing or not a number (an unfinished run's trip
    time, NaN: `compare` printed nan), right-aligned to the column's width."""
    from jaxems.cli import format_or_dash

    assert format_or_dash(None, "8.1f") == format_or_dash(float("nan"), "8.1f") == "       -"
    assert format_or_dash(float("inf"), "+9.3f") == "        -"
    assert format_or_dash(152.38, "8.1f") == "   152.4" and format_or_dash(3, "d") == "3"
