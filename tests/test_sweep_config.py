"""Sweep files, grids, chunk plans and the savings columns: no JAX compilation here."""

from __future__ import annotations

import math
import textwrap

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as hs

from jaxems import sweep as sw
from jaxems.params import load_vehicle

GOOD = """
routes = ["short_track"]
strategies = ["conventional", "baseline"]
batch_size = 4
[grid]
mass_kg = [20000, 30000, 40000]
battery_MJ = [2, 4]
"""


def write(tmp_path, text, name="s.toml"):
    p = tmp_path / name
    p.write_text(textwrap.dedent(text), encoding="utf-8")
    return p


def test_unknown_grid_key_lists_the_keys_a_grid_may_set(tmp_path):
    """The list names the user keys and the scalar vehicle fields a grid may set by name: not
    those a user key sets (mass, E_b_max, ...: refused by name) nor the curves."""
    with pytest.raises(sw.SweepError) as e:
        sw.load_config(write(tmp_path, GOOD.replace("battery_MJ", "battery_kWh")))
    fields = str(e.value).split("or a vehicle field: ")[1].rstrip(")").split(", ")
    assert "mass_kg" in str(e.value) and "c_r" in fields and "has_motor" in fields
    for refused in ("mass", "E_b_max", "soc0", "beta", "eta_e", "pm_max", "tm_max", "te_max",
                    "gear_ratio"):
        assert refused not in fields, refused


def test_good_file_parses(tmp_path):
    cfg = sw.load_config(write(tmp_path, GOOD))
    assert [r.name for r in cfg.routes] == ["short_track"]
    assert cfg.strategies == ("conventional", "baseline")
    assert cfg.grid == {"mass_kg": (20000.0, 30000.0, 40000.0), "battery_MJ": (2.0, 4.0)}
    assert cfg.grid_size == 6 and cfg.batch_size == 4 and cfg.precision == "float32"
    pts = cfg.points()
    assert pts[0] == {"mass_kg": 20000.0, "battery_MJ": 2.0}
    assert pts[1] == {"mass_kg": 20000.0, "battery_MJ": 4.0}  # first key slowest
    assert len({tuple(p.values()) for p in pts}) == 6


@pytest.mark.parametrize(
    "text, match",
    [
        ("colour = 'red'\n" + GOOD, r"s\.toml: unknown key 'colour'"),
        (GOOD.replace("battery_MJ", "battery_kWh"),
         r"s\.toml: grid\.battery_kWh: unknown grid key"),
        (GOOD.split("[grid]")[0] + "[grid]\n", r"s\.toml: grid: empty"),
        (GOOD.split("[grid]")[0], r"s\.toml: grid: empty"),
        (GOOD.replace("[2, 4]", "[]"), r"grid\.battery_MJ: empty list"),
        (GOOD.replace("20000, 30000", "0, 30000"), r"grid\.mass_kg\[0\]: must be from 1000 to"),
        (GOOD.replace("20000, 30000", "25, 30000"), r"grid\.mass_kg\[0\]: must be from 1000 to"),
        (GOOD.replace("[2, 4]", "[2, -4]"), r"grid\.battery_MJ\[1\]: must be > 0"),
        (GOOD.replace("[2, 4]", "[2, 2]"), r"grid\.battery_MJ: a value is listed twice"),
        (GOOD.replace("[2, 4]", "['two']"), r"grid\.battery_MJ\[0\]: expected a number"),
        (GOOD + "E_b_max = [1e6]\n", r"grid\.E_b_max: the vehicle's E_b_max is set by its "
                                      r"grid key in user units, battery_MJ"),
        (GOOD + "te_max = [1, 2]\n", r"grid\.te_max: te_max is a curve"),
        (GOOD + "initial_soc = [1.5]\n", r"grid\.initial_soc\[0\]: must be in \[0, 1\]"),
        (GOOD.replace('"short_track"', '"no_such_route"'),
         r"s\.toml: routes: 'no_such_route': no such route file"),
        (GOOD.replace('"short_track"', '"nothing/*.csv"'), r"routes: 'nothing/\*\.csv' matches no"),
        (GOOD.replace('"baseline"', '"magic"'), r"strategies: unknown strategy 'magic'"),
        (GOOD.replace('"baseline"', '"conventional"'), r"strategies: listed twice"),
        (GOOD.replace("batch_size = 4", "batch_size = 0"), r"batch_size: must be > 0"),
        (GOOD.replace("batch_size = 4", "batch_size = 2.5"), r"batch_size: expected a whole"),
        (GOOD + "[options.baseline]\nlam00 = -2\n", r"options\.baseline: unknown option 'lam00'"),
        (GOOD + "[options.multilevel]\nn_iter = 2\n", r"options\.multilevel: not one of"),
        (GOOD + "[options.baseline]\nn_iter = 3\n",
         r"options\.baseline: n_iter: not an option of baseline, which would ignore it"),
        (GOOD.replace("routes", "vehicle = 'no_truck'\nroutes"), r"vehicle: no_truck"),
        ("routes = [", r"not valid TOML"),
        # checked here, not in every chunk (each chunk failed with the sweep's exit status 0)
        (GOOD.replace("batch_size = 4", "dt_s = 100\nbatch_size = 4"),
         r"s\.toml: dt_s: must be a time step from 0\.05 to 10 s \(got 100\.0\)"),
        (GOOD + "we_min = [1e9]\n", r"s\.toml: grid: we_min\[0\], we_max\[0\]: the engine's "
                                    r"speed range is empty"),
        (GOOD + "[options.baseline]\nkp = inf\n", r"options\.baseline: kp: must be a finite"),
        (GOOD + "[options.baseline]\nsustain = 'maybe'\n", r"sustain: must be true or false"),
        # a chunk's arrays are padded to batch_size: 1e9 ran out of memory on one grid point
        (GOOD.replace("batch_size = 4", "batch_size = 1000000000"),
         r"batch_size: at most 65536"),
        # checked as float32 holds them: 1e39 kg ran into a JAX overflow and a crash (now
        # beyond a vehicle's mass first), 1e33 MJ into NaN fuel with status ok, 1e-50 into 0
        (GOOD.replace("20000, 30000", "20000, 1e39"),
         r"s\.toml: grid\.mass_kg\[1\]: must be from 1000 to 200000 kg"),
        (GOOD.replace("[2, 4]", "[2, 1e33]"),
         r"s\.toml: grid\.battery_MJ\[1\]: 1e\+33 is beyond what float32 holds"),
        (GOOD + "c_r = [1e-50]\n", r"grid\.c_r\[0\]: 1e-50 is beyond what float32"),
        # the vehicle file's rules: a loss coefficient that ran to NaN fuel, a motor halved
        (GOOD + "beta_per_W = [1e-50]\n", r"grid\.beta_per_W\[0\]: must be >= 1e-12"),
        (GOOD + "has_motor = [0.5]\n", r"grid\.has_motor\[0\]: must be 0 or 1"),
        # a field a user key sets, by its raw name: the results' mass_kg and battery_MJ columns
        # kept the vehicle file's values, and the report summed four vehicles in one cell
        (GOOD.replace("mass_kg", "mass"),
         r"s\.toml: grid\.mass: the vehicle's mass is set by its grid key in user units, "
         r"mass_kg .*; use mass_kg"),
        (GOOD.replace("battery_MJ = [2, 4]", "E_b_max = [2e6, 4e6]"),
         r"grid\.E_b_max: .* battery_MJ"),
        (GOOD + "soc0 = [0.5]\n", r"grid\.soc0: .* initial_soc"),
        # a raw field in SI (m/s) against the file's rule in km/h, by check_vehicle
        (GOOD + "v_cruise = [0.3]\n", r"grid: v_cruise\[0\]: must be >= 1\.8 km/h"),
        # ds_m was blamed on the route file ("short_track.csv: ds must be ...")
        (GOOD.replace("batch_size = 4", "ds_m = 0.5\nbatch_size = 4"),
         r"s\.toml: ds_m: must be from 1 to 100 m \(got 0\.5\)"),
        # grid sizes that hung load_config (1e8 values; 1e7 took 18 s and 3 GB)
        (GOOD.replace("[2, 4]", "{start = 1, stop = 5, num = 100000000}"),
         r"s\.toml: grid\.battery_MJ\.num: at most 1000000 values \(got 100000000\)"),
        (GOOD.replace("[20000, 30000, 40000]", "{start = 1e4, stop = 5e4, num = 1000}")
         .replace("[2, 4]", "{start = 1, stop = 5, num = 1001}"),
         r"s\.toml: grid: 1001000 points \(1000 mass_kg x 1001 battery_MJ\); at most 1000000"),
    ],
)
def test_bad_sweep_files_are_refused_naming_key_and_file(tmp_path, text, match):
    with pytest.raises(sw.SweepError, match=match):
        sw.load_config(write(tmp_path, text))


def test_raw_fields_in_si_against_the_file_rules(tmp_path):
    """A raw field's grid values are in SI: v_cruise = 1 m/s (3.6 km/h) is above the vehicle
    file's 1.8 km/h, though 1 < 1.8; has_motor 0 and 1 are a conventional truck and a hybrid."""
    cfg = sw.load_config(write(tmp_path, GOOD + "v_cruise = [1.0]\nhas_motor = [0, 1]\n"))
    assert cfg.grid["v_cruise"] == (1.0,) and cfg.grid["has_motor"] == (0.0, 1.0)


def test_sweep_file_not_text_or_a_directory(tmp_path):
    p = tmp_path / "x.toml"
    p.write_bytes(b"\xff\xfe routes")
    with pytest.raises(sw.SweepError, match=r"x\.toml: not UTF-8 text \(byte 0\)"):
        sw.load_config(p)
    with pytest.raises(sw.SweepError, match="a directory, not a sweep file"):
        sw.load_config(tmp_path)


def test_bad_route_file_is_named(tmp_path):
    (tmp_path / "bad.csv").write_text("distance_m,speed_limit_km_h,gradient_pct,stop_s\n"
                                      "0,25,0,0\n100,abc,0,0\n", encoding="utf-8")
    text = GOOD.replace('"short_track"', '"bad.csv"')
    with pytest.raises(sw.SweepError, match=r"routes: .*bad\.csv: line 3, column speed"):
        sw.load_config(write(tmp_path, text))


def test_a_route_or_vehicle_that_is_a_directory_is_named(tmp_path):
    """routes = ["<a directory>"] was "unknown route format ''"."""
    (tmp_path / "r.d").mkdir()
    for key, old, new, what in (("routes", '"short_track"', '"r.d"', "route"),
                                ("vehicle", "batch_size", 'vehicle = "r.d"\nbatch_size',
                                 "vehicle")):
        with pytest.raises(sw.SweepError, match=f"{key}: .*r\\.d: is a directory, not a "
                                                f"{what} file"):
            sw.load_config(write(tmp_path, GOOD.replace(old, new)))


def test_route_names_that_share_a_file_name_or_are_too_long_are_refused(tmp_path):
    """Route names stand in the chunks' and the figures' file names: "x y" and "x_y" both became
    saving_heatmap_x_y.png (one route's figure lost), and a 215-character name failed with
    "File name too long" once the first chunk had been computed."""
    text = "distance_m,speed_limit_km_h,gradient_pct,stop_s\n0,25,0,0\n100,25,0,0\n"
    for name in ("x y.csv", "x_y.csv", "r" * 101 + ".csv", "r" * 100 + ".csv"):
        (tmp_path / name).write_text(text, encoding="utf-8")
    both = GOOD.replace('"short_track"', '"x y.csv", "x_y.csv"')
    with pytest.raises(sw.SweepError, match=r"routes: two route files named 'x_y' or alike "
                                            r"\(as 'x_y' in file names\)"):
        sw.load_config(write(tmp_path, both))
    long = GOOD.replace('"short_track"', f'"{"r" * 101}.csv"')
    with pytest.raises(sw.SweepError, match=r"a name of 101 characters; at most 100"):
        sw.load_config(write(tmp_path, long))
    ok = sw.load_config(write(tmp_path, GOOD.replace('"short_track"', f'"{"r" * 100}.csv"')))
    assert [r.name for r in ok.routes] == ["r" * 100]


def test_bad_input_stops_before_any_computation(tmp_path, capsys):
    """The CLI exits 1 with one line naming the key; no results directory is created."""
    out = tmp_path / "out"
    p = write(tmp_path, GOOD.replace("20000, 30000", "0, 30000"))
    assert sw.main([str(p), "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert "grid.mass_kg[0]: must be from 1000 to 200000 kg" in err and "s.toml" in err
    assert not out.exists()


def test_float32_range_of_vehicle_values():
    """The vehicle file's values are held in the sweep's precision too (`_check_precision`)."""
    with pytest.raises(sw.SweepError, match=r"^v: vehicle\.mass_kg: 1e\+39 is beyond what "
                                            r"float32 holds .*precision = \"float64\""):
        sw._check_precision(1e39, 1.0, "float32", "v: vehicle.mass_kg", indexed=False)
    with pytest.raises(sw.SweepError, match=r"^v: te_max\[2\]: 1e\+39 is beyond"):
        sw._check_precision([1.0, 2.0, 1e39], 1.0, "float32", "v: te_max")
    sw._check_precision([1e39, 0.0, -5.0], 1.0, "float64", "v")  # float64 holds them
    with pytest.raises(sw.SweepError, match=r"grid\.battery_MJ\[0\]: 1e\+33 .*3\.4e\+32"):
        sw._check_precision([1e33], 1e6, "float32", "grid.battery_MJ")  # in MJ, 1e39 J


@pytest.mark.parametrize(
    "kw, out, words",
    [
        ({"workers": 0}, "out", "--workers: expected a whole number >= 1 (got 0)"),
        ({"scheduler": "nonsense"}, "out",
         "--scheduler: 'nonsense' is not a Dask scheduler address, expected tcp://HOST:PORT"),
        ({}, "afile", "--out: {tmp}/afile is not a directory"),
        ({}, "afile/sub", "--out: {tmp}/afile is not a directory (in {tmp}/afile/sub)"),
    ],
)
def test_bad_flags_stop_before_the_directory_is_made(tmp_path, capsys, monkeypatch, kw, out,
                                                     words):
    """--workers, --scheduler and --out are checked before prepare_dir writes anything (the
    directory and sweep.json were made, then `--workers 0` refused; `--out afile` said only
    "[Errno 20] Not a directory: 'afile/chunks'")."""
    pytest.importorskip("distributed")
    monkeypatch.setattr(sw, "_in_process_devices", lambda n: None)  # this process's devices
    p = write(tmp_path, GOOD)
    (tmp_path / "afile").write_text("")
    with pytest.raises(sw.SweepError) as e:
        sw.run_sweep(p, tmp_path / out, quiet=True, **kw)
    assert str(e.value).startswith(words.replace("{tmp}", str(tmp_path)))
    assert sorted(x.name for x in tmp_path.iterdir()) == ["afile", "s.toml"]
    argv = [str(p), "--out", str(tmp_path / out)] + [f"--{k}={v}" for k, v in kw.items()]
    assert sw.main(argv) == 1  # the command: one line naming the flag
    err = capsys.readouterr().err
    assert err.startswith("jaxems: error: --") and err.count("\n") == 1
    assert sorted(x.name for x in tmp_path.iterdir()) == ["afile", "s.toml"]


def test_an_unreachable_scheduler_leaves_no_directory(tmp_path, monkeypatch):
    """--scheduler naming no scheduler failed after its timeout (as it should) but left a
    skeleton results directory (sweep.toml, sweep.json, .lock, chunks/): the scheduler is
    reached first; a sweep's existing directory is left as it was."""
    pytest.importorskip("distributed")
    monkeypatch.setattr(sw, "SCHEDULER_TIMEOUT_S", 1)
    p = write(tmp_path, GOOD)
    with pytest.raises(sw.SweepError, match="cannot reach the Dask scheduler at "
                                            "tcp://127.0.0.1:1"):
        sw.run_sweep(p, tmp_path / "out", scheduler="tcp://127.0.0.1:1", quiet=True)
    assert sorted(x.name for x in tmp_path.iterdir()) == ["s.toml"]
    out = tmp_path / "done"
    sw.prepare_dir(sw.load_config(p), out)
    before = sorted(x.name for x in out.rglob("*"))
    with pytest.raises(sw.SweepError, match="cannot reach the Dask scheduler"):
        sw.run_sweep(p, out, scheduler="tcp://127.0.0.1:1", quiet=True, resume=True)
    assert sorted(x.name for x in out.rglob("*")) == before


def test_globs_relative_paths_and_ranges(tmp_path):
    d = tmp_path / "routes"
    d.mkdir()
    src = sw.load_config(write(tmp_path, GOOD)).routes[0].path.read_text(encoding="utf-8")
    for n in ("a", "b"):
        (d / f"{n}.csv").write_text(src, encoding="utf-8")
    text = GOOD.replace('["short_track"]', '["routes/*.csv", "routes/a.csv", "short_track"]')
    text = text.replace("[2, 4]", "{start = 2, stop = 6, num = 3}")
    cfg = sw.load_config(write(tmp_path, text))
    assert [r.name for r in cfg.routes] == ["a", "b", "short_track"]  # a listed twice: once
    assert cfg.grid["battery_MJ"] == (2.0, 4.0, 6.0)


def test_fingerprint_ignores_comments_but_not_values(tmp_path):
    a = sw.load_config(write(tmp_path, GOOD, "a.toml"))
    b = sw.load_config(write(tmp_path, "# a comment\n" + GOOD, "b.toml"))
    c = sw.load_config(write(tmp_path, GOOD.replace("40000", "45000"), "c.toml"))
    assert a.fingerprint() == b.fingerprint() != c.fingerprint()


def test_changed_sweep_in_existing_directory_is_refused(tmp_path):
    out = tmp_path / "out"
    sw.prepare_dir(sw.load_config(write(tmp_path, GOOD)), out)
    sw.prepare_dir(sw.load_config(write(tmp_path, "# comment only\n" + GOOD)), out)  # same
    changed = sw.load_config(write(tmp_path, GOOD.replace("40000", "45000")))
    with pytest.raises(sw.SweepError, match=r"holds the results of a different sweep "
                                            r"\(changed: grid;.*another --out"):
        sw.prepare_dir(changed, out)
    with pytest.raises(sw.SweepError, match="nothing to resume"):
        sw.prepare_dir(changed, tmp_path / "fresh", resume=True)
    # the grid's keys swapped: the same points in another order, so that a chunk's grid_index
    # names other points (a resume mixed the two orders, and the savings compared a baseline
    # at 20 t / 4 MJ with a conventional truck at 30 t / 2 MJ)
    swapped = GOOD.replace("mass_kg = [20000, 30000, 40000]\nbattery_MJ = [2, 4]",
                           "battery_MJ = [2, 4]\nmass_kg = [20000, 30000, 40000]")
    assert swapped != GOOD
    reordered = sw.load_config(write(tmp_path, swapped))
    assert reordered.grid == sw.load_config(write(tmp_path, GOOD, "a.toml")).grid
    with pytest.raises(sw.SweepError, match=r"different sweep \(changed: the grid's key order "
                                            r"\(the first key varies slowest"):
        sw.prepare_dir(reordered, out)


def test_an_out_directory_that_cannot_be_made_names_the_flag(tmp_path, monkeypatch):
    """Where `check_out_dir` passes and the directory still cannot be made (root, under /proc:
    "[Errno 2] No such file or directory: '/proc/x'" named no flag), the error names --out."""
    cfg = sw.load_config(write(tmp_path, GOOD))

    def refused(self, *a, **k):
        raise FileNotFoundError(2, "No such file or directory", str(self))

    monkeypatch.setattr(sw.Path, "mkdir", refused)
    with pytest.raises(sw.SweepError, match=r"--out: cannot make .*out \(No such file or "
                                            r"directory\)"):
        sw.prepare_dir(cfg, tmp_path / "out")


def test_a_run_killed_while_it_makes_its_directory_runs_again(tmp_path, monkeypatch):
    """chunks/ was made before sweep.json: a run killed in between left a directory that a
    rerun refused ("holds sweep results without sweep.json") and --resume did not know."""
    cfg = sw.load_config(write(tmp_path, GOOD))
    out = tmp_path / "out"
    write_bytes = sw.atomic_write_bytes

    def killed_at_the_record(path, data):
        if path.name == sw.CONFIG_FILE:
            raise KeyboardInterrupt
        write_bytes(path, data)

    monkeypatch.setattr(sw, "atomic_write_bytes", killed_at_the_record)
    with pytest.raises(KeyboardInterrupt):
        sw.prepare_dir(cfg, out)
    monkeypatch.undo()
    assert not (out / "chunks").exists()
    sw.prepare_dir(cfg, out)  # starts afresh
    assert (out / "sweep.json").exists() and (out / "chunks").is_dir()
    (out / "chunks").rmdir()  # killed after the record: the rerun makes chunks/
    sw.prepare_dir(cfg, out, resume=True)
    assert (out / "chunks").is_dir()
    # such a directory from an earlier jaxems: an empty chunks/, no record -> fresh
    half = tmp_path / "half"
    (half / "chunks").mkdir(parents=True)
    sw.prepare_dir(cfg, half)
    assert (half / "sweep.json").exists()
    # finished chunks without a record are still refused
    other = tmp_path / "other"
    (other / "chunks").mkdir(parents=True)
    (other / "chunks" / "x.parquet").write_bytes(b"x")
    with pytest.raises(sw.SweepError, match="holds sweep results without sweep.json"):
        sw.prepare_dir(cfg, other)


def test_a_folder_that_is_no_sweeps_is_not_written_into(tmp_path, capsys, monkeypatch):
    """--out naming a folder of the user's (not empty, no sweep.json) wrote its report.html
    over the user's and added its files; --out '' wrote into the current directory."""
    monkeypatch.setattr(sw, "_in_process_devices", lambda n: None)  # this process's devices
    cfg = sw.load_config(write(tmp_path, GOOD))
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "report.html").write_text("mine")
    (foreign / "notes").mkdir()
    for extra in ([], [sw.SOURCE_COPY]):  # a sweep.toml of other text is the user's too
        if extra:
            (foreign / "report.html").unlink()
            (foreign / "notes").rmdir()
            (foreign / sw.SOURCE_COPY).write_text("# another sweep\n" + GOOD)
        before = {p.name: p.read_bytes() if p.is_file() else None for p in foreign.iterdir()}
        with pytest.raises(sw.SweepError) as e:
            sw.prepare_dir(cfg, foreign)
        assert str(e.value).startswith(f"--out: {foreign} is not empty and holds no jaxems "
                                       f"sweep (no sweep.json; it has "
                                       f"{', '.join(sorted(before))})")
        assert {p.name: p.read_bytes() if p.is_file() else None
                for p in foreign.iterdir()} == before
    p = write(tmp_path, GOOD)
    for out, words in ((str(foreign), f"--out: {foreign} is not empty"),
                       ("", "--out: expected a directory name (got '')")):
        assert sw.main([str(p), "--out", out, "--quiet"]) == 1
        err = capsys.readouterr().err
        assert err.startswith(f"jaxems: error: {words}") and err.count("\n") == 1
    assert sorted(x.name for x in tmp_path.iterdir()) == ["foreign", "s.toml"]
    # an empty folder, and one a killed run of this sweep left (its sweep.toml): fresh
    (tmp_path / "empty").mkdir()
    sw.prepare_dir(cfg, tmp_path / "empty")
    (foreign / sw.SOURCE_COPY).write_text(cfg.text)
    sw.prepare_dir(cfg, foreign)
    assert (foreign / sw.CONFIG_FILE).exists() and (tmp_path / "empty" / sw.CONFIG_FILE).exists()


def test_results_of_other_code_are_refused_and_the_demo_starts_over(tmp_path, monkeypatch,
                                                                      capsys):
    cfg = sw.load_config(write(tmp_path, GOOD))
    out = tmp_path / "out"
    sw.prepare_dir(cfg, out)
    (out / "chunks" / "x.parquet").write_bytes(b"old")
    sw._set_aside_if_other(cfg, out)  # the same sweep by the same code: kept
    assert (out / "chunks" / "x.parquet").exists() and capsys.readouterr().out == ""
    assert len(sw.code_sha256()) == 64
    monkeypatch.setattr(sw, "code_sha256", lambda: "0" * 64)  # jaxems changed since
    with pytest.raises(sw.SweepError, match=r"different sweep \(changed: code \(computed by "
                                            r"another version of jaxems\)"):
        sw.prepare_dir(cfg, out)
    sw._set_aside_if_other(cfg, out)
    assert "moved to" in capsys.readouterr().out and not out.exists()
    assert (tmp_path / "out.stale" / "chunks" / "x.parquet").read_bytes() == b"old"
    sw.prepare_dir(cfg, out)  # starts over
    assert list((out / "chunks").iterdir()) == []


def test_grid_keys_map_to_si_fields():
    base = load_vehicle()
    pts = [{"mass_kg": 25000.0, "battery_MJ": 3.0, "motor_power_kW": 100.0,
            "motor_torque_Nm": 400.0, "beta_per_W": 2e-6, "engine_efficiency": 0.4,
            "initial_soc": 0.3, "c_r": 0.005}] * 3
    vb = sw.vehicle_batch(base, pts)
    assert all(np.shape(x)[:1] == (3,) for x in vb)  # every leaf batched
    np.testing.assert_array_equal(vb.mass, 25000.0)
    np.testing.assert_array_equal(vb.E_b_max, 3e6)
    np.testing.assert_array_equal(vb.pm_max, 1e5)
    np.testing.assert_array_equal(vb.tm_max, 400.0)
    np.testing.assert_array_equal(vb.beta, 2e-6)
    np.testing.assert_array_equal(vb.eta_e, 0.4)
    np.testing.assert_array_equal(vb.soc0, 0.3)
    np.testing.assert_array_equal(vb.c_r, 0.005)
    np.testing.assert_array_equal(vb.gear_ratio, np.broadcast_to(base.gear_ratio, (3, 12)))
    np.testing.assert_array_equal(vb.v_cruise, base.v_cruise)


@settings(max_examples=30)
@given(sizes=hs.lists(hs.integers(1, 4), min_size=1, max_size=3), batch=hs.integers(1, 7),
       n_strat=hs.integers(1, 3))
def test_chunks_cover_every_point_once_with_equal_shapes(tmp_path_factory, sizes, batch,
                                                         n_strat):
    tmp = tmp_path_factory.mktemp("plan")
    keys = ["mass_kg", "battery_MJ", "motor_power_kW"][: len(sizes)]
    grid = "\n".join(f"{k} = {[float(10 + i) * (1e3 if k == 'mass_kg' else 1) for i in range(n)]}"
                     for k, n in zip(keys, sizes, strict=True))
    strat = ["conventional", "baseline", "multilevel"][:n_strat]
    text = (f"routes = ['short_track']\nstrategies = {strat}\nbatch_size = {batch}\n"
            f"[grid]\n{grid}\n")
    cfg = sw.load_config(write(tmp, text))
    chunks = sw.plan_chunks(cfg)
    G = math.prod(sizes)
    assert len(chunks) == n_strat * math.ceil(G / batch)
    assert len({c.id for c in chunks}) == len(chunks)
    assert [c.id for c in sw.plan_chunks(cfg)] == [c.id for c in chunks]  # deterministic
    for s in strat:
        mine = [c for c in chunks if c.strategy == s]
        real = [i for c in mine for i in c.grid_index[: c.n_real]]
        assert sorted(real) == list(range(G))  # every point exactly once
        assert all(len(c.grid_index) == min(batch, G) for c in mine)  # one shape per route
        assert all(set(c.grid_index[c.n_real:]) <= {c.grid_index[c.n_real - 1]} for c in mine)


def test_a_grid_smaller_than_batch_size_is_not_padded_to_it(tmp_path):
    """1 point with batch_size = 4096 computed 4096 runs; one chunk, one shape, either way."""
    text = GOOD.replace("batch_size = 4", "batch_size = 4096").replace("[2, 4]", "[2]")
    chunks = sw.plan_chunks(sw.load_config(write(tmp_path, text)))
    assert [(len(c.grid_index), c.n_real) for c in chunks] == [(3, 3), (3, 3)]


def _savings_reference(df: pd.DataFrame, ref: str) -> np.ndarray:
    """Plain loop: saving of each row against `ref` on the same route and grid point."""
    out = np.full(len(df), np.nan)
    rows = df.to_dict("records")

    def corrected(r):
        lam, dE = r["lambda_b"], r["delta_Eb_J"]
        if r["strategy"] == "conventional" or not (np.isfinite(lam) and np.isfinite(dE)):
            return r["fuel_J"]
        return r["fuel_J"] + lam * dE

    for i, r in enumerate(rows):
        for q in rows:
            if (q["route"], q["grid_index"], q["strategy"]) == (r["route"], r["grid_index"], ref):
                if r["status"] == "ok" and q["status"] == "ok":
                    out[i] = 100.0 * (corrected(q) - corrected(r)) / corrected(q)
    return out


def test_savings_against_a_loop_reference():
    rng = np.random.default_rng(3)
    rows = []
    for route in ("a", "b"):
        for g in range(3):
            for s in ("conventional", "baseline", "multilevel"):
                if route == "b" and g == 2 and s == "conventional":
                    continue  # reference missing -> NaN
                rows.append({
                    "route": route, "grid_index": g, "strategy": s,
                    "fuel_J": rng.uniform(5e6, 2e7),
                    "lambda_b": np.nan if s == "conventional" else rng.uniform(-3, -1),
                    "delta_Eb_J": 0.0 if s == "conventional" else rng.uniform(-1e6, 1e6),
                    "status": "infeasible-route" if (route, g, s) == ("a", 1, "baseline")
                    else "ok",
                })
    df = sw.add_savings(pd.DataFrame(rows))
    for ref in ("conventional", "baseline"):
        np.testing.assert_allclose(df[f"saving_vs_{ref}_pct"].to_numpy(),
                                   _savings_reference(df, ref), rtol=1e-12, equal_nan=True)
    # sanity of the reference itself: the reference strategy saves exactly 0 against itself
    conv = df[(df.strategy == "conventional") & (df.status == "ok")]
    np.testing.assert_array_equal(conv["saving_vs_conventional_pct"], 0.0)
    assert df["saving_vs_conventional_pct"].isna().sum() == 3  # b/2: no reference; a/1 failed
