"""Sweeps with the real strategies on small problems: batching, compile counts, resume, status,
CLI output and the Dask backend on a local two-process cluster.

One sweep (two short routes of the same shape bucket, `conventional`, 6 grid points in chunks of
4) is computed once per test process (module fixture); the other tests rerun parts of it, which
reuses the compiled kernel (same shapes).
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest

from jaxems import report as rp
from jaxems import strategies as st
from jaxems import sweep as sw
from jaxems.levels.velocity import velocity_profile

STEEP = """distance_m,speed_limit_km_h,gradient_pct,stop_s
0,25,0,0
100,25,25,0
150,25,0,0
300,25,0,0
"""
SWEEP_A = """
description = "test sweep A"
routes = ["short_track", "steep_climb.csv"]
strategies = ["conventional"]
batch_size = 4
precision = "float64"
[grid]
mass_kg = [20000, 30000, 60000]
battery_MJ = [2, 4]
"""
TIMING = ["wall_s"]  # the only column that may differ between runs


def make_sweep_a(d):
    """Write sweep A (and its steep route: 25 % over 50 m, too steep for 60 t) into d."""
    d.mkdir(parents=True, exist_ok=True)
    (d / "steep_climb.csv").write_text(STEEP, encoding="utf-8")
    p = d / "sweep_a.toml"
    p.write_text(textwrap.dedent(SWEEP_A), encoding="utf-8")
    return p


def same_table(a: pd.DataFrame, b: pd.DataFrame) -> None:
    pd.testing.assert_frame_equal(a.drop(columns=TIMING), b.drop(columns=TIMING),
                                  check_exact=True)


@pytest.fixture(scope="module")
def sweep_a(tmp_path_factory):
    d = tmp_path_factory.mktemp("sweep_a")
    p = make_sweep_a(d)
    summary = sw.run_sweep(p, d / "out", quiet=True)
    return p, d / "out", summary


def test_table_has_one_row_per_route_point_strategy(sweep_a):
    p, out, summary = sweep_a
    df = sw.load_sweep(out)
    cfg = sw.load_config(p)
    assert len(df) == 2 * 6 * 1 == summary.n_configs
    assert not df.duplicated(["route", "grid_index", "strategy"]).any()
    assert list(df["route"].unique()) == ["short_track", "steep_climb"]
    pts = cfg.points()
    for r in df.itertuples():
        assert (r.mass_kg, r.battery_MJ) == (pts[r.grid_index]["mass_kg"],
                                             pts[r.grid_index]["battery_MJ"])
    for col in [*sw.RESULT_FIELDS, "status", "wall_s", "fuel_corrected_J",
                "saving_vs_conventional_pct", "saving_vs_baseline_pct"]:
        assert col in df.columns
    np.testing.assert_allclose(df[df.route == "short_track"]["length_m"], 1055.0)
    assert (out / "results.parquet").exists() and (out / "report.html").exists()
    # conventional against itself: 0 % where ok; no baseline in this sweep: NaN
    ok = df["status"] == "ok"
    np.testing.assert_array_equal(df.loc[ok, "saving_vs_conventional_pct"], 0.0)
    assert df["saving_vs_baseline_pct"].isna().all()


def test_infeasible_route_is_recorded_and_the_sweep_goes_on(sweep_a):
    _, out, summary = sweep_a
    df = sw.load_sweep(out)
    steep = df[df.route == "steep_climb"].set_index("mass_kg")["status"]
    assert (steep.loc[60000.0] != "ok").all()
    assert steep.loc[60000.0].str.contains("infeasible-route").all()
    assert (steep.loc[20000.0] == "ok").all()
    assert (df[df.route == "short_track"]["status"] == "ok").all()
    assert summary.status_counts.get("ok", 0) >= 8
    from jaxems.report import charge_missed, trip_long

    assert summary.charge_missed == int(charge_missed(df).sum())
    assert f"{summary.charge_missed} end more than 1 % of their battery" in summary.text()
    assert summary.trip_long == int(trip_long(df).sum())
    assert f"{summary.trip_long} take more than 1 % longer than Level 3's" in summary.text()
    assert (df["level3_trip_time_s"] > 0).all()  # the column is in the results


def test_one_compilation_per_strategy_and_bucket_not_per_chunk(sweep_a):
    """Four chunks (2 routes in the same 512-node / 256-step bucket x 2 grid chunks): only the
    first one compiles; new masses and battery sizes and the padded last chunk reuse it."""
    _, _, summary = sweep_a
    stats = summary.chunk_stats
    assert len(stats) == 4
    assert stats[0]["compiles"] > 0
    assert [s["compiles"] for s in stats[1:]] == [0, 0, 0]


def test_rows_equal_a_direct_simulate_batch_call(sweep_a):
    """The padded last chunk of steep_climb: rows == simulate_batch on the same batch."""
    p, out, _ = sweep_a
    cfg = sw.load_config(p)
    chunk = [c for c in sw.plan_chunks(cfg) if c.route_index == 1][-1]
    assert chunk.n_real == 2 and chunk.grid_index == (4, 5, 5, 5)
    pts = cfg.points()
    vb = sw.vehicle_batch(cfg.vehicle, [pts[i] for i in chunk.grid_index])
    route = cfg.routes[1].route
    with sw.precision_scope("float64"):
        n_steps = sw.steps_for_route(cfg, route, [chunk], pts)
        direct = st.simulate_batch(route, vb, "conventional", dt=1.0, n_steps=n_steps)
    df = sw.load_sweep(out)
    rows = df[(df.route == "steep_climb") & (df.grid_index >= 4)]
    for f in sw.RESULT_FIELDS:
        np.testing.assert_array_equal(rows[f].to_numpy(), np.asarray(direct[f])[:2], err_msg=f)
    assert list(rows["status"]) == [str(s) for s in direct["status"][:2]]


def test_a_chunk_whose_strategy_raises_gets_error_rows(sweep_a, monkeypatch):
    """An exception inside the strategy does not stop the sweep: every real row of the chunk
    gets status 'error: ...' (type and message), no fuel, the route's length, and no Level 2
    (`strategies.NO_LEVEL2`)."""
    p, _, _ = sweep_a
    cfg = sw.load_config(p)
    chunk = [c for c in sw.plan_chunks(cfg) if c.route_index == 1][-1]
    pts = cfg.points()
    task = sw.ChunkTask(chunk=chunk, vehicles=sw.vehicle_batch(
        cfg.vehicle, [pts[i] for i in chunk.grid_index]), dt=1.0, n_steps=64,
        precision="float64", options=None)

    def boom(*a, **k):
        raise FloatingPointError("the plant\nfell over")

    monkeypatch.setattr(st, "simulate_batch", boom)
    route = cfg.routes[1].route
    rows = sw.compute_chunk(task, route)
    n = chunk.n_real
    assert list(rows["status"]) == ["error: FloatingPointError: the plant fell over"] * n
    assert np.isnan(rows["fuel_J"]).all() and (rows["mode_switches"] == 0).all()
    assert (rows["level2_status"] == st.NO_LEVEL2).all()
    assert (rows["length_m"] == float(np.asarray(route.length))).all()

    def too_big(*a, **k):  # XLA out of memory: its first line and what shrinks the chunk
        raise jax.errors.JaxRuntimeError("RESOURCE_EXHAUSTED: Out of memory allocating 42 "
                                         "bytes.\nmore of XLA's text")

    monkeypatch.setattr(st, "simulate_batch", too_big)
    rows = sw.compute_chunk(task, route)
    assert list(rows["status"]) == [
        "error: out of memory (RESOURCE_EXHAUSTED: Out of memory allocating 42 bytes.); a "
        "smaller batch_size, a larger dt_s or smaller size options need less"] * n


def test_rerun_and_resume_compute_only_what_is_missing(sweep_a, tmp_path, capsys):
    p, out, _ = sweep_a
    full = sw.load_sweep(out)
    d = tmp_path / "copy"
    shutil.copytree(out, d)
    chunks = sorted((d / "chunks").glob("*.parquet"))
    chunks[1].unlink()  # a lost chunk
    stale = d / "chunks" / f".{chunks[2].name}.tmp-999-1"
    stale.write_bytes(b"half a parquet file")  # left by a killed writer
    assert sw.main([str(p), "--out", str(d), "--resume"]) == 0
    io = capsys.readouterr()
    assert "cfg/s" in io.err  # progress bar on stderr
    assert "computed 2 configurations (1 chunks)" in io.out and "3 chunks already done" in io.out
    assert not stale.exists()
    same_table(sw.load_sweep(d), full)
    # a plain rerun of a complete sweep computes nothing; --quiet: no progress bar
    assert sw.main([str(p), "--out", str(d), "--quiet"]) == 0
    io = capsys.readouterr()
    assert io.err == "" and "computed 0 configurations (0 chunks)" in io.out
    same_table(sw.load_sweep(d), full)


def test_a_finished_sweep_needs_no_scheduler(sweep_a, tmp_path, monkeypatch):
    """A finished sweep run again with --scheduler writes its results and report again without
    reaching the scheduler (the scheduler, reached first, failed it once the cluster was gone);
    a sweep with a chunk left reaches it first and fails, its directory as it was."""
    pytest.importorskip("distributed")
    monkeypatch.setattr(sw, "SCHEDULER_TIMEOUT_S", 1)
    p, out, _ = sweep_a
    d = tmp_path / "copy"
    shutil.copytree(out, d)
    (d / "report.html").unlink()
    summary = sw.run_sweep(p, d, scheduler="tcp://127.0.0.1:1", quiet=True)
    assert summary.computed_chunks == 0 and (d / "report.html").exists()
    same_table(sw.load_sweep(d), sw.load_sweep(out))
    sorted((d / "chunks").glob("*.parquet"))[0].unlink()
    before = sorted(x.name for x in d.rglob("*"))
    with pytest.raises(sw.SweepError, match="cannot reach the Dask scheduler at "
                                            "tcp://127.0.0.1:1"):
        sw.run_sweep(p, d, scheduler="tcp://127.0.0.1:1", quiet=True)
    assert sorted(x.name for x in d.rglob("*")) == before
    # a chunk gone between the look and the lock: the scheduler's still, not in-process
    monkeypatch.setattr(sw, "_chunks_left", lambda cfg, out: False)
    with pytest.raises(sw.SweepError, match="cannot reach the Dask scheduler"):
        sw.run_sweep(p, d, scheduler="tcp://127.0.0.1:1", quiet=True)


def test_damaged_results_are_named(sweep_a, tmp_path):
    # a chunk file or the sweep record damaged outside jaxems (its own writes are whole): an
    # error naming the file and what to do, not pyarrow's or json's message alone
    p, out, _ = sweep_a
    d = tmp_path / "damaged"
    shutil.copytree(out, d)
    (d / sw.RESULTS_FILE).unlink()  # the chunks are read
    chunk = sorted((d / "chunks").glob("*.parquet"))[0]
    chunk.write_bytes(chunk.read_bytes()[:100])
    with pytest.raises(sw.SweepError, match=rf"{re.escape(chunk.name)}: unreadable chunk file"
                                            rf".*delete it.*--resume"):
        sw.load_sweep(d)
    chunk.unlink()
    (d / sw.CONFIG_FILE).write_text("{'canonical': ", encoding="utf-8")
    with pytest.raises(sw.SweepError, match=rf"{sw.CONFIG_FILE}: unreadable sweep record"):
        rp.write_report(d)


def test_changed_sweep_file_is_refused_by_the_cli(sweep_a, tmp_path, capsys):
    p, out, _ = sweep_a
    d = tmp_path / "copy"
    shutil.copytree(out, d)
    q = tmp_path / "changed.toml"
    shutil.copy(p.parent / "steep_climb.csv", tmp_path / "steep_climb.csv")
    q.write_text(p.read_text().replace("batch_size = 4", "batch_size = 3"), encoding="utf-8")
    before = sorted(x.name for x in (d / "chunks").iterdir())
    assert sw.main([str(q), "--out", str(d)]) == 1
    err = capsys.readouterr().err
    assert "holds the results of a different sweep (changed: batch_size" in err
    assert sorted(x.name for x in (d / "chunks").iterdir()) == before


def test_report_of_the_sweep_is_self_contained(sweep_a):
    _, out, _ = sweep_a
    page = rp.write_report(out)
    text = page.read_text(encoding="utf-8")
    # conventional only: no savings to map, the fuel figure only
    assert text.count("data:image/png;base64,") == 1 and (out / "fuel_per_strategy.png").exists()
    assert "http://" not in text and "https://" not in text
    assert "steep_climb" in text and "infeasible-route" in text


def test_precision_scope_sets_and_restores():
    before = jnp.zeros(()).dtype
    with sw.precision_scope("float32"):
        assert jnp.zeros(()).dtype == jnp.float32
        assert jnp.asarray(np.float64(1.0)).dtype == jnp.float32
    with sw.precision_scope("float64"):
        assert jnp.zeros(()).dtype == jnp.float64
    assert jnp.zeros(()).dtype == before


def test_dask_two_worker_processes_give_the_same_table(sweep_a, tmp_path):
    """Chunks sent to a running cluster (the --scheduler path) of two worker processes on
    loopback; the workers run float64 because the sweep says so (the test process's x64 setting
    does not reach them)."""
    distributed = pytest.importorskip("dask.distributed")
    p, out, _ = sweep_a
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  host="127.0.0.1", dashboard_address=None) as cluster:
        summary = sw.run_sweep(p, tmp_path / "dask", scheduler=cluster.scheduler_address,
                               quiet=True, report=False)
    assert summary.backend == "Dask, 2 workers"
    assert summary.computed_chunks == 4
    same_table(sw.load_sweep(tmp_path / "dask"), sw.load_sweep(out))
    assert jax.config.jax_enable_x64  # the test process's own setting is untouched


def test_local_cluster_of_the_command_shares_its_compilation_cache(tmp_path):
    """`jaxems sweep --workers N`, as a user runs it: the workers, spawned from the `jaxems`
    script, import JAX before Dask sets their environment, and still cache their kernels in
    DIR/jax-cache (they compiled every kernel anew before)."""
    pytest.importorskip("dask.distributed")
    script = Path(sys.executable).parent / "jaxems"
    if not script.exists():
        pytest.skip("the jaxems script is not installed beside this Python")
    p = tmp_path / "one.toml"
    p.write_text('routes = ["short_track"]\nstrategies = ["conventional"]\nbatch_size = 2\n'
                 '[grid]\nmass_kg = [20000, 30000]\n', encoding="utf-8")
    env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
    done = subprocess.run([str(script), "sweep", str(p), "--out", str(tmp_path / "out"),
                           "--workers", "1", "--quiet", "--no-report"], env=env,
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    assert any((tmp_path / "out" / "jax-cache").iterdir())


def test_eco_strategy_in_a_sweep_gets_room_for_its_own_trip(tmp_path):
    """multilevel-eco is one more strategy of the sweep file; its step grid has room for a
    trip eco_time_ratio times Level 3's (matched within 0.5 %)."""
    d = tmp_path / "eco"
    p = make_sweep_a(d)
    text = p.read_text(encoding="utf-8").replace(
        'strategies = ["conventional"]', 'strategies = ["conventional", "multilevel-eco"]')
    p.write_text(text + '\n[options.multilevel-eco]\neco_time_ratio = 1.3\n', encoding="utf-8")
    cfg = sw.load_config(p)
    assert "multilevel-eco" in cfg.strategies
    chunk = [c for c in sw.plan_chunks(cfg) if c.route_index == 0][0]
    pts = cfg.points()
    vb = sw.vehicle_batch(cfg.vehicle, [pts[i] for i in chunk.grid_index])
    route = cfg.routes[0].route
    with sw.precision_scope("float64"):
        n_eco = sw.steps_for_route(cfg, route, [chunk], pts)
        n_l3 = st.steps_for_batch(route, vb, 1.0)
        trip = max(float(velocity_profile(route, jax.tree_util.tree_map(lambda a: a[i], vb))
                         .trip_time) for i in range(len(chunk.grid_index)))
    assert n_eco >= 1.3 * trip and n_eco >= n_l3
    p.write_text(text + '\n[options.multilevel-eco]\neco_time_ratio = 0.5\n', encoding="utf-8")
    with pytest.raises(sw.SweepError, match="eco_time_ratio"):
        sw.load_config(p)
