"""A sweep process killed with SIGKILL and resumed gives the table of an uninterrupted run."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pandas as pd
import pytest

from jaxems import sweep as sw

SWEEP_B = """
routes = ["short_track"]
strategies = ["conventional", "baseline"]
batch_size = 4
precision = "float64"
[grid]
mass_kg = [20000, 30000, 40000]
battery_MJ = [2, 4]
"""


def _cli() -> list[str]:
    """`python -m jaxems sweep` once the CLI has the subcommand, else `python -m jaxems.sweep`."""
    from jaxems.cli import build_parser

    sub = next(a for a in build_parser()._actions if a.dest == "command")
    if "sweep" in sub.choices:
        return [sys.executable, "-m", "jaxems", "sweep"]
    return [sys.executable, "-m", "jaxems.sweep"]


@pytest.mark.skipif(not hasattr(signal, "SIGKILL"), reason="needs SIGKILL")
def test_kill_9_then_resume_equals_uninterrupted(tmp_path):
    p = tmp_path / "sweep_b.toml"
    p.write_text(textwrap.dedent(SWEEP_B), encoding="utf-8")
    killed, ref = tmp_path / "killed", tmp_path / "reference"
    cmd = _cli()

    # 1. start, and kill -9 as soon as the first chunk file is there
    proc = subprocess.Popen([*cmd, str(p), "--out", str(killed), "--quiet"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    chunk_dir = killed / "chunks"
    t0 = time.monotonic()
    while proc.poll() is None and time.monotonic() - t0 < 240:
        if chunk_dir.is_dir() and any(not f.name.startswith(".")
                                      for f in chunk_dir.iterdir()):
            os.kill(proc.pid, signal.SIGKILL)
            break
        time.sleep(0.01)
    proc.wait(timeout=60)
    assert proc.returncode == -signal.SIGKILL, proc.stderr.read().decode()[-2000:]
    done_at_kill = sw.finished_chunks(killed)
    assert 0 < len(done_at_kill) < 4  # killed in the middle: work was left
    assert not (killed / "results.parquet").exists()

    # 2. resume: only the missing chunks are computed
    res = subprocess.run([*cmd, str(p), "--out", str(killed), "--resume", "--quiet"],
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    assert f"{len(done_at_kill)} chunks already done" in res.stdout
    assert res.stderr == ""  # --quiet: no progress bar

    # 3. an uninterrupted run, with its progress bar and summary
    res = subprocess.run([*cmd, str(p), "--out", str(ref)], capture_output=True,
                         text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    assert "cfg/s" in res.stderr
    assert "computed 12 configurations (4 chunks)" in res.stdout
    assert f"report:  {ref / 'report.html'}" in res.stdout

    a, b = sw.load_sweep(killed), sw.load_sweep(ref)
    assert len(a) == 12 and not a.duplicated(["route", "grid_index", "strategy"]).any()
    pd.testing.assert_frame_equal(a.drop(columns=["wall_s"]), b.drop(columns=["wall_s"]),
                                  check_exact=True)

    # savings of the real strategies: the formula, row by row against the references
    for ref_s in ("conventional", "baseline"):
        r = a[a.strategy == ref_s].set_index("grid_index")
        f_ref = r["fuel_corrected_J"].loc[a.grid_index].to_numpy()
        expect = 100.0 * (f_ref - a.fuel_corrected_J.to_numpy()) / f_ref
        expect[(a.status != "ok").to_numpy()] = np.nan
        expect[(r["status"].loc[a.grid_index] != "ok").to_numpy()] = np.nan
        np.testing.assert_allclose(a[f"saving_vs_{ref_s}_pct"], expect, rtol=1e-12,
                                   equal_nan=True)
    conv = a[a.strategy == "conventional"]
    np.testing.assert_array_equal(conv.fuel_corrected_J, conv.fuel_J)
    base = a[a.strategy == "baseline"]
    np.testing.assert_allclose(base.fuel_corrected_J,
                               base.fuel_J + base.lambda_b * base.delta_Eb_J, rtol=1e-12)
