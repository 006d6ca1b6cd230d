"""Sweep reports on synthetic results (no JAX): fleet savings, best battery, the HTML page."""

from __future__ import annotations

import base64
import itertools
import json
import re
import warnings

import numpy as np
import pandas as pd
import pytest

from jaxems import report as rp
from jaxems import sweep as sw

MASSES = (20000.0, 30000.0, 40000.0)
BATTERIES = (2.0, 4.0, 8.0)
ROUTES = ("hilly", "flat")
STRATS = ("conventional", "baseline", "multilevel")


def synthetic(seed=0, drop=()):
    """A results table shaped like load_sweep's, with fuel falling with battery size."""
    rng = np.random.default_rng(seed)
    rows = []
    for r, route in enumerate(ROUTES):
        for g, (m, b) in enumerate(itertools.product(MASSES, BATTERIES)):
            conv = 1e7 * (1 + r) * m / 20000 * rng.uniform(0.95, 1.05)
            for s in STRATS:
                if (route, g, s) in drop:
                    continue
                k = {"conventional": 1.0, "baseline": 0.93, "multilevel": 0.9}[s]
                fuel = conv * (k - (0 if s == "conventional" else 0.01 * np.log(b)))
                rows.append({
                    "route": route, "strategy": s, "grid_index": g, "mass_kg": m,
                    "battery_MJ": b, "length_m": 1e4 * (1 + r),
                    "trip_time_s": 600.0 + float(rng.integers(0, 16)), "level3_trip_time_s": 597.0,
                    "fuel_J": fuel, "fuel_l_per_100km": fuel / 42.8e6 / 0.832 / (0.1 * (1 + r)),
                    "delta_Eb_J": 0.0 if s == "conventional" else rng.uniform(-1e5, 1e5),
                    "Eb_min_J": 0.0, "Eb_max_J": b * 1e6, "mode_switches": 3,
                    "gear_switches": 7, "lambda_b": np.nan if s == "conventional" else -2.0,
                    "max_speed_shortfall_mps": 0.1,
                    "level2_status": -1 if s != "multilevel" else int(rng.choice([0, 2, 4, 6])),
                    "status": "infeasible-route" if (route, g) == ("hilly", 8) else "ok",
                    "wall_s": 0.01, "chunk": f"{route}-{s}",
                })
    return sw.add_savings(pd.DataFrame(rows))


def write_dir(tmp_path, df):
    """A sweep directory holding df as chunk files and a sweep.json for its grid."""
    canon = {"format": 1, "routes": [{"name": r, "sha256": "0"} for r in dict.fromkeys(df.route)],
             "strategies": list(STRATS),
             "grid": {"mass_kg": list(MASSES), "battery_MJ": list(BATTERIES)}}
    d = tmp_path / "sweep"
    (d / "chunks").mkdir(parents=True)
    (d / "sweep.json").write_text(json.dumps({"fingerprint": "x", "canonical": canon}))
    for (route, s), g in df.groupby(["route", "strategy"]):
        g.drop(columns=["fuel_corrected_J", "saving_vs_conventional_pct",
                        "saving_vs_baseline_pct"]).to_parquet(d / "chunks" / f"{route}-{s}.parquet")
    return d


def test_load_sweep_merges_chunks_in_sweep_order(tmp_path):
    df = synthetic()
    d = write_dir(tmp_path, df)
    got = sw.load_sweep(d)
    assert list(got["route"].unique()) == list(ROUTES)
    assert list(got["strategy"][:3]) == list(STRATS)
    assert (np.diff(got[got.route == "hilly"]["grid_index"].to_numpy()) >= 0).all()
    key = ["route", "grid_index", "strategy"]
    pd.testing.assert_frame_equal(
        got.sort_values(key).reset_index(drop=True)[df.columns],
        df.sort_values(key).reset_index(drop=True), check_exact=False, rtol=1e-12)


def test_fleet_saving_and_best_battery_against_loops():
    df = synthetic(1)
    fleet = rp.fleet_saving(df, "conventional")
    assert len(fleet) == len(STRATS) * len(MASSES) * len(BATTERIES)
    for row in fleet.itertuples():
        num = den = 0.0
        all_ok = True
        for route in ROUTES:
            sel = (df.route == route) & (df.mass_kg == row.mass_kg) & (df.battery_MJ ==
                                                                      row.battery_MJ)
            a = df[sel & (df.strategy == row.strategy)]
            c = df[sel & (df.strategy == "conventional")]
            all_ok &= a.status.iloc[0] == "ok" and c.status.iloc[0] == "ok"
            num += c.fuel_corrected_J.iloc[0] - a.fuel_corrected_J.iloc[0]
            den += c.fuel_corrected_J.iloc[0]
        if all_ok:
            assert row.saving_pct == pytest.approx(100 * num / den, rel=1e-12)
        else:  # hilly at 40 t / 8 MJ did not finish: no fleet number for that cell
            assert (row.mass_kg, row.battery_MJ) == (40000.0, 8.0) and np.isnan(row.saving_pct)
    assert fleet.saving_pct.isna().sum() == len(STRATS)
    best = rp.best_battery(fleet[fleet.strategy != "conventional"])
    # 40 t has a cell without a fleet saving: its best would be the best of the other two
    assert len(best) == 2 * (len(MASSES) - 1) and 40000.0 not in set(best.mass_kg)
    for row in best.itertuples():
        f = fleet[(fleet.strategy == row.strategy) & (fleet.mass_kg == row.mass_kg)]
        top = f.saving_pct.max()
        assert row.best_saving_pct == top
        assert row.best_battery_MJ == f.loc[f.saving_pct.idxmax(), "battery_MJ"]
        close = f[f.saving_pct >= top - rp.SUFFICIENT_PP]
        assert row.sufficient_battery_MJ == close.battery_MJ.min()
        assert row.sufficient_battery_MJ <= row.best_battery_MJ


def test_fleet_saving_of_an_unfinished_sweep_is_blank_where_a_route_is_missing():
    # a cell's pairs are its routes times the grid's other points (here 2 routes): where the
    # sweep has not computed one of them yet, the cell has no fleet saving (it summed the
    # routes there were, as if complete)
    df = synthetic(5, drop={("flat", g, "multilevel") for g in range(3)})  # 20 t, 3 batteries
    fleet = rp.fleet_saving(df, "conventional", n_per_cell=len(ROUTES))
    ml = fleet[fleet.strategy == "multilevel"]
    missing = ml.mass_kg == 20000.0
    assert ml[missing].saving_pct.isna().all() and (ml[missing].n_total == 2).all()
    assert ml[~missing & (ml.battery_MJ < 8.0)].saving_pct.notna().all()
    assert rp.fleet_saving(df, "conventional")[missing.reindex(fleet.index, fill_value=False)
                                                ].saving_pct.notna().all()  # without the count


def test_table_cells_keep_every_digit_of_whole_numbers():
    assert [rp._fmt(x) for x in (20000.0, 40004.0, 12345.0, 99999.0)] == [
        "20000", "40004", "12345", "99999"]
    assert rp._fmt(13174.25) == "13174.2" and rp._fmt(-1.98765) == "-1.988"
    assert rp._fmt(float("nan")) == "" and rp._fmt("a<b") == "a&lt;b"


def test_report_of_one_strategy_has_no_empty_fleet_table(tmp_path):
    df = synthetic(6)
    df = df[df.strategy.isin(["conventional"])]
    text = rp.write_report(write_dir(tmp_path, df)).read_text(encoding="utf-8")
    assert "fleet saving against" not in text and "<tbody>\n\n</tbody>" not in text


def test_report_page_is_self_contained_with_every_figure(tmp_path, capsys):
    d = write_dir(tmp_path, synthetic())
    assert rp.main([str(d)]) == 0
    page = d / "report.html"
    assert capsys.readouterr().out.strip() == str(page)
    text = page.read_text(encoding="utf-8")
    pngs = {rp.FLEET_HEATMAP, "saving_heatmap_hilly.png",
            "saving_heatmap_flat.png", "fuel_per_strategy.png", "saving_distribution.png",
            "best_battery.png"}
    assert {p.name for p in d.glob("*.png")} == pngs
    embedded = re.findall(r'src="data:image/png;base64,([A-Za-z0-9+/=]+)"', text)
    assert len(embedded) == len(pngs)
    assert {base64.b64decode(e) for e in embedded} == {(d / n).read_bytes() for n in pngs}
    assert not re.search(r'(src|href)="(https?:)?//', text)  # nothing to fetch
    assert "<script" not in text
    assert "infeasible-route" in text  # the failed configuration is listed
    assert "best battery per mass" in text


def test_level2_running_out_of_pieces_is_counted():
    """Finished runs whose Level 2 flags hold pieces-exhausted (bit 4 of level2_status; -1: no
    Level 2), counted per route and strategy as a loop over the rows counts them; a table
    without the column counts none."""
    df = synthetic(4)
    want = {}
    for row in df.itertuples():
        hit = row.status == "ok" and row.level2_status >= 0 and (row.level2_status & 4) > 0
        want[(row.route, row.strategy)] = want.get((row.route, row.strategy), 0) + hit
    got = rp.summary_table(df, "conventional")
    assert {(r.route, r.strategy): r.level2_exhausted for r in got.itertuples()} == want
    assert sum(want.values()) > 0 and all(want[(r, "baseline")] == 0 for r in ROUTES)
    old = rp.summary_table(df.drop(columns=["level2_status"]), "conventional")
    assert (old["level2_exhausted"] == 0).all()


def check_counted_and_listed(tmp_path, df, flagged, column, caption):
    """The rows `flagged(row)` (a loop over them) are the summary table's `column` per route and
    strategy, and the report's list of them says how many (caption: a regex whose groups are
    the count and how many are listed). Returns the count per (route, strategy)."""
    want = {}
    for row in df.itertuples():
        hit = row.status == "ok" and flagged(row)
        want[(row.route, row.strategy)] = want.get((row.route, row.strategy), 0) + hit
    got = rp.summary_table(df, "conventional")
    assert {(r.route, r.strategy): getattr(r, column) for r in got.itertuples()} == want
    n = sum(want.values())
    assert 0 < n < len(df)
    text = rp.write_report(write_dir(tmp_path, df)).read_text(encoding="utf-8")
    found = re.search(caption, text)
    assert found and int(found.group(1)) == n
    assert int(found.group(2)) == min(n, rp.MAX_MISSED)
    return want


def test_charge_misses_are_counted_and_listed(tmp_path):
    """Finished runs that end more than 1 % of their battery from their start: counted per
    route and strategy (a loop over the rows), the largest listed in the page."""
    want = check_counted_and_listed(
        tmp_path, synthetic(3), lambda row: abs(row.delta_Eb_J) > 0.01 * row.battery_MJ * 1e6,
        "charge_missed",
        r"end more than 1 % of their battery from where they started \((\d+); the (\d+) largest\)")
    assert all(want[(r, "conventional")] == 0 for r in ROUTES)


def test_long_trips_are_counted_and_listed(tmp_path):
    """Finished runs whose trip takes more than 1 % longer than their Level 3 prediction:
    counted per route and strategy (a loop over the rows), the longest listed in the page; a
    table without Level 3's trip time (a sweep written before it) counts none."""
    df = synthetic(5)
    check_counted_and_listed(
        tmp_path, df, lambda row: row.trip_time_s > 1.01 * row.level3_trip_time_s, "trip_long",
        r"trip takes more than 1 % longer than the Level 3 prediction they followed "
        r"\((\d+); the (\d+) longest")
    old = rp.summary_table(df.drop(columns=["level3_trip_time_s"]), "conventional")
    assert (old["trip_long"] == 0).all()


def test_report_of_an_unfinished_sweep_and_without_references(tmp_path):
    drop = {(r, g, s) for r in ROUTES for g in range(9) for s in ("conventional", "baseline")}
    df = synthetic(2, drop=drop)  # multilevel only: no reference strategy
    d = write_dir(tmp_path, df)
    page = rp.write_report(d)
    text = page.read_text(encoding="utf-8")
    assert "Unfinished sweep" in text
    assert (d / "fuel_per_strategy.png").exists()
    assert not (d / rp.FLEET_HEATMAP).exists()


def test_report_of_a_missing_directory_is_an_error(tmp_path, capsys):
    assert rp.main([str(tmp_path / "nothing")]) == 1
    assert "not a jaxems sweep directory" in capsys.readouterr().err


def test_a_corrupt_results_file_is_named_with_what_to_do(tmp_path, capsys):
    """A results.parquet damaged outside jaxems gave pyarrow's message alone."""
    d = write_dir(tmp_path, synthetic())
    (d / sw.RESULTS_FILE).write_bytes(b"PAR1 not parquet")  # newer than every chunk
    assert rp.main([str(d)]) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"jaxems: error: {d / sw.RESULTS_FILE}: not a readable Parquet file (")
    assert "delete it and run the sweep again with --resume" in err and err.count("\n") == 1


def test_load_sweep_merges_again_where_a_chunk_file_is_gone(tmp_path):
    """results.parquet is the merged chunks while they are the same: a chunk file deleted
    since (to recompute it) was still reported ("12 of 12 configurations")."""
    d = write_dir(tmp_path, synthetic())
    sw.load_sweep(d).to_parquet(d / sw.RESULTS_FILE)  # newer than every chunk
    assert len(sw.load_sweep(d)) == len(synthetic())
    (d / "chunks" / "flat-baseline.parquet").unlink()
    got = sw.load_sweep(d)
    assert len(got) == len(synthetic()) - len(MASSES) * len(BATTERIES)
    assert not ((got.route == "flat") & (got.strategy == "baseline")).any()


def test_route_names_are_text_in_the_figures_and_the_fleet_keeps_its_own(tmp_path):
    """A route named all_routes wrote its heatmap over the fleet's (the same file name), and a
    $ in a route's name made matplotlib read mathematics and fail after the sweep had run."""
    df = synthetic(3)
    df = df.assign(route=df.route.replace({"hilly": "all_routes", "flat": "A$_$B"}))
    d = write_dir(tmp_path, df)
    rp.write_report(d)
    names = {p.name for p in d.glob("*.png")}
    assert {rp.FLEET_HEATMAP, "saving_heatmap_all_routes.png", "saving_heatmap_A___B.png"} <= names
    assert (d / rp.FLEET_HEATMAP).read_bytes() != (d / "saving_heatmap_all_routes.png").read_bytes()


def test_best_battery_of_a_tie_is_the_smaller_one():
    """Two batteries with which the runs take the same decisions give savings that differ in
    their last bits (16.87588125207177 and ...181): the smaller battery is the best."""
    fleet = pd.DataFrame({"strategy": "baseline", "mass_kg": 25000.0,
                          "battery_MJ": [2.0, 4.0, 8.0],
                          "saving_pct": [16.87588125207177, 16.87588125207181, 10.0]})
    best = rp.best_battery(fleet)
    assert best.best_battery_MJ.tolist() == [2.0] and best.sufficient_battery_MJ.tolist() == [2.0]


def test_heatmap_keeps_a_mass_whose_runs_all_failed():
    """A mass whose every cell is blank (a climb no run of 40 t finished) is a blank row, not a
    row left out under a title that says blank means a run did not finish."""
    df = synthetic(4)
    ml = df[df.strategy == "multilevel"]
    ml = ml.assign(saving_vs_conventional_pct=np.where(ml.mass_kg == 40000.0, np.nan,
                                                       ml.saving_vs_conventional_pct))
    tab = rp._pivot(ml, "saving_vs_conventional_pct")
    assert list(tab.index) == list(MASSES) and tab.loc[40000.0].isna().all()


def test_a_sweep_of_one_battery_size_has_no_best_battery(tmp_path):
    """Over mass alone the best battery per mass can only be the vehicle's own: no table, no
    figure."""
    df = synthetic(7)
    df = df[df.battery_MJ == 4.0]
    d = write_dir(tmp_path, df)
    text = rp.write_report(d).read_text(encoding="utf-8")
    assert "best battery per mass" not in text and not (d / "best_battery.png").exists()
    assert (d / rp.FLEET_HEATMAP).exists()
    assert rp._text("_depot") == " _depot" and rp._text("a$b") == r"a\$b"


def test_a_reference_that_burns_no_fuel_leaves_the_saving_blank_without_warnings():
    """An all-downhill route run without fuel: 0 / 0 warned on stderr and read as a run that
    did not finish; now blank, for a reason the captions name."""
    df = synthetic(8)
    df.loc[df.route == "flat", "fuel_J"] = 0.0
    df.loc[df.route == "flat", "delta_Eb_J"] = 0.0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = sw.add_savings(df.drop(columns=["fuel_corrected_J", "saving_vs_conventional_pct",
                                              "saving_vs_baseline_pct"]))
        fleet = rp.fleet_saving(out[out.route == "flat"], "conventional")
    assert out[out.route == "flat"]["saving_vs_conventional_pct"].isna().all()
    assert out[out.route == "hilly"]["saving_vs_conventional_pct"].notna().any()
    assert fleet.saving_pct.isna().all()

