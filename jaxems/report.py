"""Sweep reports: PNG figures and one self-contained ``report.html`` (matplotlib, Agg).

    jaxems report DIR        (also run at the end of `jaxems sweep`)

Writes into DIR (a sweep results directory, see `jaxems.sweep`):

- ``saving_heatmap_<route>.png``: saving (%) over mass x battery size, one panel per strategy,
  for each route;
- ``fleet_saving_heatmap.png``: the fleet saving over mass x battery size, from the fuel
  summed over all routes (every route counts with its fuel, i.e. its length and load);
- ``fuel_per_strategy.png``: corrected fuel (l/100 km) per strategy per route, mean over the
  grid, with the range over the grid as error bars;
- ``saving_distribution.png``: distribution of the savings over routes and grid points;
- ``best_battery.png``: for each mass, the battery size with the largest fleet saving and the
  smallest one within `SUFFICIENT_PP` percentage points of it;
- ``report.html``: all of the above embedded as base64 data URIs, plus tables of the numbers
  (opens without network access).

Savings are those of `jaxems.sweep.add_savings` (corrected fuel), against ``conventional`` when
the sweep ran it, otherwise against ``baseline``. Grid parameters other than mass and battery
size are averaged over in the figures (the tables list them).
"""

from __future__ import annotations

import base64
import html
import sys
import time
from pathlib import Path

import numpy as np

SUFFICIENT_PP = 0.5  # percentage points: "sufficient" battery = within this of the best saving
TIE_PP = 1e-9  # percentage points: savings this close are the same (the best battery's tie)
FLEET_HEATMAP = "fleet_saving_heatmap.png"  # its own name: a route may be named all_routes
MAX_FULL_TABLE = 2000  # rows: the full results table goes into the page up to this size
MAX_MISSED = 50  # rows: the largest charge misses listed in the page
CHARGE_SHARE = 0.01  # a run misses the charge beyond this share of its battery (|delta_Eb|)
TRIP_SHARE = 0.01  # a trip is long beyond this share over Level 3's (level3_trip_time_s)


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_png(fig, path, dpi: int = 100) -> Path:
    """Write a figure as a PNG, whole or not at all (`sweep.atomic_write_bytes`), and close
    it."""
    import io

    from .sweep import atomic_write_bytes

    buf = io.BytesIO()
    fig.savefig(buf, dpi=dpi, format="png")
    _plt().close(fig)
    atomic_write_bytes(Path(path), buf.getvalue())
    return Path(path)


def _text(name: str) -> str:
    """A name as plain text in a figure: matplotlib reads $...$ as mathematics, and leaves a
    legend entry whose label starts with _ out."""
    name = name.replace("$", r"\$")
    return " " + name if name.startswith("_") else name


def reference_strategy(df) -> str | None:
    """The strategy savings are shown against: conventional if run, else baseline, else None."""
    present = set(df["strategy"])
    for ref in ("conventional", "baseline"):
        if ref in present:
            return ref
    return None


def _strategies(df) -> list[str]:
    return list(dict.fromkeys(df["strategy"]))


def _routes(df) -> list[str]:
    return list(dict.fromkeys(df["route"]))


def corrected_l_per_100km(df) -> np.ndarray:
    """Corrected fuel in l/100 km: fuel_l_per_100km scaled by fuel_corrected_J / fuel_J."""
    f = df["fuel_J"].to_numpy(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = np.where(f > 0, df["fuel_corrected_J"].to_numpy(np.float64) / f, np.nan)
    return df["fuel_l_per_100km"].to_numpy(np.float64) * scale


def fleet_saving(df, ref: str, n_per_cell: int | None = None):
    """Fleet saving (%) per (strategy, mass_kg, battery_MJ): 100 (sum F_ref - sum F) / sum F_ref.

    Sums of corrected fuel over routes and over the other grid parameters. A cell counts only
    when every one of its (route, grid point) pairs finished with status ok for both the
    strategy and the reference, and, where n_per_cell is given (the sweep's routes times its
    other grid points), all of them are there (an unfinished sweep lacks some); otherwise its
    saving is NaN (a fleet saving over a subset of the routes would not be comparable between
    cells), as it is where the reference's summed fuel is not positive (nothing to save).
    Returns a DataFrame with columns strategy, mass_kg, battery_MJ, saving_pct, n (pairs ok),
    n_total (pairs the cell holds, n_per_cell where given).
    """
    import pandas as pd

    cols = ["strategy", "mass_kg", "battery_MJ", "saving_pct", "n", "n_total"]
    refs = df[df["strategy"] == ref][["route", "grid_index", "fuel_corrected_J", "status"]]
    refs = refs.rename(columns={"fuel_corrected_J": "F_ref", "status": "status_ref"})
    m = df.merge(refs, on=["route", "grid_index"], how="left")
    rows = []
    for (s, mass, bat), g in m.groupby(["strategy", "mass_kg", "battery_MJ"], sort=True):
        ok = (g["status"] == "ok") & (g["status_ref"] == "ok")
        total = len(g) if n_per_cell is None else n_per_cell
        fr = g["F_ref"].sum()
        whole = ok.all() and len(g) == total
        sav = 100.0 * (fr - g["fuel_corrected_J"].sum()) / fr if whole and fr > 0 else np.nan
        rows.append({"strategy": s, "mass_kg": mass, "battery_MJ": bat, "saving_pct": sav,
                     "n": int(ok.sum()), "n_total": total})
    return pd.DataFrame(rows, columns=cols)


def best_battery(fleet) -> object:
    """Per (strategy, mass): the battery with the largest fleet saving, and the smallest battery
    whose saving is within `SUFFICIENT_PP` percentage points of it. A mass with a battery whose
    cell has no fleet saving (a run that did not finish, an unfinished sweep) is left out: its
    best would be the best of the others; and a fleet of one battery size has none (it would be
    that size)."""
    import pandas as pd

    rows = []
    one_size = fleet["battery_MJ"].nunique() < 2
    for (s, mass), g in ([] if one_size else fleet.groupby(["strategy", "mass_kg"])):
        if g["saving_pct"].isna().any():
            continue
        g = g.sort_values("battery_MJ")
        x = g["saving_pct"].to_numpy()
        # the smallest battery of the largest saving: runs that take the same decisions with
        # two batteries differ in their savings' last bits
        best = g.iloc[int(np.argmax(x >= np.max(x) - TIE_PP))]
        suff = g[g["saving_pct"] >= best["saving_pct"] - SUFFICIENT_PP].iloc[0]
        rows.append({"strategy": s, "mass_kg": mass, "best_battery_MJ": best["battery_MJ"],
                     "best_saving_pct": best["saving_pct"],
                     "sufficient_battery_MJ": suff["battery_MJ"],
                     "sufficient_saving_pct": suff["saving_pct"]})
    return pd.DataFrame(rows, columns=["strategy", "mass_kg", "best_battery_MJ",
                                       "best_saving_pct", "sufficient_battery_MJ",
                                       "sufficient_saving_pct"])


# --------------------------------------------------------------------------------- figures
def _heatmap(ax, table, title: str, vlim: float):
    """table: DataFrame index mass_kg, columns battery_MJ, values saving %."""
    from matplotlib.colors import TwoSlopeNorm

    z = table.to_numpy(np.float64)
    norm = TwoSlopeNorm(vcenter=0.0, vmin=-vlim, vmax=vlim)
    im = ax.imshow(z, origin="lower", aspect="auto", cmap="RdYlGn", norm=norm)
    ax.set_xticks(range(z.shape[1]), [f"{x:g}" for x in table.columns])
    ax.set_yticks(range(z.shape[0]), [f"{y / 1000:g}" for y in table.index])
    ax.set_xlabel("battery (MJ)")
    ax.set_ylabel("mass (t)")
    ax.set_title(title, fontsize=9)
    if z.size <= 150:
        for (i, j), v in np.ndenumerate(z):
            if np.isfinite(v):
                ax.text(j, i, f"{v:.1f}", ha="center", va="center", fontsize=7)
    return im


def _heatmap_figure(path: Path, panels: list[tuple[str, object]], suptitle: str) -> bool:
    plt = _plt()
    panels = [(t, tab) for t, tab in panels if tab.size and np.isfinite(tab.to_numpy()).any()]
    if not panels:
        return False
    vals = np.concatenate([tab.to_numpy(np.float64).ravel() for _, tab in panels])
    vlim = max(float(np.nanmax(np.abs(vals))), 1e-3)
    n = len(panels)
    fig, axes = plt.subplots(1, n, figsize=(3.6 * n + 1.2, 3.4), squeeze=False,
                             constrained_layout=True)
    im = None
    for ax, (title, tab) in zip(axes[0], panels, strict=True):
        im = _heatmap(ax, tab, title, vlim)
    fig.colorbar(im, ax=axes[0].tolist(), label="saving (%)")
    fig.suptitle(suptitle, fontsize=10)
    save_png(fig, path)
    return True


def _pivot(df, col: str):
    """mass x battery table of col (mean over the other grid keys); a mass or battery whose
    cells are all blank (runs that did not finish) stays, blank."""
    return df.pivot_table(index="mass_kg", columns="battery_MJ", values=col, aggfunc="mean",
                          dropna=False)


def plot_route_heatmaps(out: Path, df, ref: str) -> list[Path]:
    """One PNG per route: saving vs `ref` over mass x battery, a panel per other strategy."""
    from .sweep import safe_name

    paths = []
    col = f"saving_vs_{ref}_pct"
    others = [s for s in _strategies(df) if s != ref]
    for r in _routes(df):
        d = df[df["route"] == r]
        panels = [(f"{s} vs {ref}", _pivot(d[d["strategy"] == s], col)) for s in others]
        p = out / f"saving_heatmap_{safe_name(r)}.png"
        if _heatmap_figure(p, panels, f"{_text(r)}: fuel saving (%) against {ref}"):
            paths.append(p)
    return paths


def plot_fleet_heatmap(out: Path, fleet, ref: str) -> Path | None:
    """Fleet saving over mass x battery (fuel summed over all routes), a panel per strategy."""
    panels = []
    for s in dict.fromkeys(fleet["strategy"]):
        if s == ref:
            continue
        d = fleet[fleet["strategy"] == s]
        panels.append((f"{s} vs {ref}", _pivot(d, "saving_pct")))
    p = out / FLEET_HEATMAP
    ok = _heatmap_figure(p, panels, f"all routes: fleet fuel saving (%) against {ref}\n"
                              f"(blank: a route did not finish, or {ref} burned no fuel)")
    return p if ok else None


def plot_fuel(out: Path, df) -> Path | None:
    """Grouped bars: corrected fuel (l/100 km) per route and strategy (mean, min-max bars)."""
    plt = _plt()
    d = df[df["status"] == "ok"].assign(l100=lambda x: corrected_l_per_100km(x))
    if d.empty:
        return None
    routes, strats = _routes(df), _strategies(df)
    fig, ax = plt.subplots(figsize=(max(6.0, 1.2 * len(routes) * max(1, len(strats)) * 0.5 + 3),
                                    4.0), constrained_layout=True)
    w = 0.8 / len(strats)
    for j, s in enumerate(strats):
        mean, lo, hi = [], [], []
        for r in routes:
            x = d[(d["route"] == r) & (d["strategy"] == s)]["l100"].to_numpy()
            x = x[np.isfinite(x)]
            mean.append(x.mean() if x.size else np.nan)
            lo.append(x.min() if x.size else np.nan)
            hi.append(x.max() if x.size else np.nan)
        mean, lo, hi = map(np.asarray, (mean, lo, hi))
        xs = np.arange(len(routes)) + (j - (len(strats) - 1) / 2) * w
        ax.bar(xs, mean, w, label=s, color=f"C{j}")
        ax.errorbar(xs, mean, yerr=[mean - lo, hi - mean], fmt="none", ecolor="0.2", lw=0.8,
                    capsize=2)
    ax.set_xticks(range(len(routes)), [_text(r) for r in routes],
                  rotation=20 if len(routes) > 4 else 0)
    ax.set_ylabel("fuel, corrected (l/100 km)")
    ax.set_title("fuel per strategy and route (mean over the grid; bars: range over the grid)",
                 fontsize=9)
    ax.legend(fontsize=8)
    p = out / "fuel_per_strategy.png"
    save_png(fig, p)
    return p


def plot_distribution(out: Path, df, ref: str) -> Path | None:
    """Box plot per strategy of the savings over all routes and grid points; route means."""
    plt = _plt()
    col = f"saving_vs_{ref}_pct"
    strats = [s for s in _strategies(df) if s != ref]
    data = [df[df["strategy"] == s][col].dropna().to_numpy() for s in strats]
    if not strats or not any(x.size for x in data):
        return None
    fig, ax = plt.subplots(figsize=(max(5.0, 1.6 * len(strats) + 2), 4.0),
                           constrained_layout=True)
    ax.boxplot([x if x.size else [np.nan] for x in data], tick_labels=strats, showfliers=False)
    rng = np.random.default_rng(0)
    for k, r in enumerate(_routes(df)):
        for j, s in enumerate(strats):
            y = df[(df["strategy"] == s) & (df["route"] == r)][col].dropna().to_numpy()
            if y.size:
                ax.scatter(j + 1 + rng.uniform(-0.15, 0.15, y.size), y, s=8, alpha=0.5,
                           color=f"C{k % 10}", label=_text(r) if j == 0 else None)
    ax.axhline(0, color="0.5", lw=0.6)
    ax.set_ylabel(f"saving against {ref} (%)")
    ax.set_title("distribution of savings over routes (points: route x grid point)", fontsize=9)
    if len(_routes(df)) <= 12:
        ax.legend(fontsize=7, loc="best")
    p = out / "saving_distribution.png"
    save_png(fig, p)
    return p


def plot_best_battery(out: Path, best) -> Path | None:
    """Best and sufficient battery size per mass, a line per strategy."""
    plt = _plt()
    if best.empty:
        return None
    fig, ax = plt.subplots(figsize=(6.0, 4.0), constrained_layout=True)
    for j, s in enumerate(dict.fromkeys(best["strategy"])):
        d = best[best["strategy"] == s].sort_values("mass_kg")
        ax.plot(d["mass_kg"] / 1000, d["best_battery_MJ"], "o-", color=f"C{j}",
                label=f"{s}: largest saving")
        ax.plot(d["mass_kg"] / 1000, d["sufficient_battery_MJ"], "s--", color=f"C{j}",
                alpha=0.6, label=f"{s}: within {SUFFICIENT_PP:g} pp")
    ax.set_xlabel("mass (t)")
    ax.set_ylabel("battery (MJ)")
    ax.set_title("best battery size per mass (fleet saving over all routes)", fontsize=9)
    ax.legend(fontsize=7)
    p = out / "best_battery.png"
    save_png(fig, p)
    return p


# ------------------------------------------------------------------------------------ html
def _fmt(x) -> str:
    if isinstance(x, float | np.floating):
        if not np.isfinite(x):
            return ""
        if x == int(x) and abs(x) < 1e15:  # grid values, counts: every digit (20000, 40004)
            return f"{x:.0f}"
        return f"{x:.4g}" if abs(x) < 1e3 else f"{x:.6g}"
    return html.escape(str(x))


def _table(df, caption: str = "") -> str:
    head = "".join(f"<th>{html.escape(str(c))}</th>" for c in df.columns)
    body = "\n".join("<tr>" + "".join(f"<td>{_fmt(v)}</td>" for v in row) + "</tr>"
                     for row in df.itertuples(index=False))
    cap = f"<caption>{html.escape(caption)}</caption>" if caption else ""
    return f"<table>{cap}<thead><tr>{head}</tr></thead><tbody>\n{body}\n</tbody></table>"


def _img(path: Path, alt: str) -> str:
    data = base64.b64encode(path.read_bytes()).decode("ascii")
    return (f'<figure><img alt="{html.escape(alt)}" src="data:image/png;base64,{data}">'
            f"<figcaption>{html.escape(alt)} ({path.name})</figcaption></figure>")


_CSS = """
body { font-family: sans-serif; margin: 1.5em; max-width: 1300px; color: #222; }
table { border-collapse: collapse; margin: 0.8em 0; font-size: 12px; }
th, td { border: 1px solid #ccc; padding: 2px 6px; text-align: right; }
th { background: #eee; } caption { text-align: left; font-weight: bold; padding: 4px 0; }
figure { display: inline-block; margin: 0.5em; } img { max-width: 100%; }
figcaption { font-size: 11px; color: #555; } .note { color: #555; font-size: 13px; }
"""


def off_charge(delta_Eb_J, E_b_max_J, share: float = CHARGE_SHARE):
    """Whether a run's battery balance (J, end minus start; arrays or scalars) is more than
    share of its battery (J) from zero: the charge-sustaining check."""
    return np.abs(np.asarray(delta_Eb_J, float)) > share * np.asarray(E_b_max_J, float)


def charge_missed(df, share: float = CHARGE_SHARE):
    """(len(df),) bool: finished runs that end more than share of their battery (battery_MJ)
    from where they started (their corrected fuel prices the difference at lambda_b)."""
    return ((df["status"] == "ok").to_numpy()
            & off_charge(df["delta_Eb_J"].to_numpy(float),
                         df["battery_MJ"].to_numpy(float) * 1e6, share))


def trip_vs_level3_pct(trip_time_s, level3_trip_time_s):
    """How much longer a trip took than the Level 3 prediction it followed, in % (arrays or
    scalars; nan where there is no prediction, a trip time of 0)."""
    t3 = np.asarray(level3_trip_time_s, float)
    ok = t3 > 0
    return np.where(ok, 100.0 * (np.asarray(trip_time_s, float) / np.where(ok, t3, 1.0) - 1.0),
                    np.nan)


def trip_long(df, share: float = TRIP_SHARE):
    """(len(df),) bool: finished runs whose trip takes more than share longer than Level 3's
    prediction it followed (`level3_trip_time_s`; False where the column is absent, as in
    sweeps written before it)."""
    if "level3_trip_time_s" not in df:
        return np.zeros(len(df), bool)
    t3 = df["level3_trip_time_s"].to_numpy(float)
    return ((df["status"] == "ok").to_numpy() & (t3 > 0)
            & (df["trip_time_s"].to_numpy(float) > (1.0 + share) * t3))


def level2_exhausted(df):
    """(len(df),) bool: finished runs whose last plan's Level 2 ran out of pieces with the
    battery's limits still violated (`level2_status`; False where the column is absent)."""
    from .levels.battery import PIECES_EXHAUSTED

    if "level2_status" not in df:
        return np.zeros(len(df), bool)
    code = df["level2_status"].to_numpy(np.int64)
    return (df["status"] == "ok").to_numpy() & (code >= 0) & ((code & PIECES_EXHAUSTED) > 0)


def summary_table(df, ref: str | None):
    """Per route and strategy: rows, ok rows, rows that miss the charge (`charge_missed`),
    rows whose trip is long against Level 3's (`trip_long`), rows whose Level 2 ran out of
    pieces (`level2_exhausted`), mean fuel and mean/min/max saving."""
    import pandas as pd

    rows = []
    missed = charge_missed(df)
    long = trip_long(df)
    exhausted = level2_exhausted(df)
    for r in _routes(df):
        for s in _strategies(df):
            sel = ((df["route"] == r) & (df["strategy"] == s)).to_numpy()
            d = df[sel]
            ok = d[d["status"] == "ok"]
            row = {"route": r, "strategy": s, "rows": len(d), "ok": len(ok),
                   "charge_missed": int(np.sum(missed & sel)),
                   "trip_long": int(np.sum(long & sel)),
                   "level2_exhausted": int(np.sum(exhausted & sel)),
                   "fuel_corrected_MJ_mean": ok["fuel_corrected_J"].mean() / 1e6 if len(ok)
                   else np.nan,
                   "fuel_corrected_l_per_100km_mean": np.nanmean(corrected_l_per_100km(ok))
                   if len(ok) else np.nan}
            if ref is not None:
                sv = d[f"saving_vs_{ref}_pct"].dropna()
                row |= {f"saving_vs_{ref}_mean_pct": sv.mean() if len(sv) else np.nan,
                        f"saving_vs_{ref}_min_pct": sv.min() if len(sv) else np.nan,
                        f"saving_vs_{ref}_max_pct": sv.max() if len(sv) else np.nan}
            rows.append(row)
    return pd.DataFrame(rows)


def write_report(directory: str | Path, df=None) -> Path:
    """Write the PNGs and ``report.html`` into a sweep directory; returns the HTML path.

    df: the results (default `jaxems.sweep.load_sweep(directory)`); an unfinished sweep gives a
    report of the rows so far.
    """
    from .sweep import atomic_write_bytes, load_sweep, read_record

    out = Path(directory)
    if df is None:
        df = load_sweep(out)
    meta = read_record(out)
    canon = meta["canonical"]
    ref = reference_strategy(df)
    figs: list[tuple[Path, str]] = []
    fleet = best = None
    # the (route, grid point) pairs of a fleet cell: routes x the grid's other points
    per_cell = len(canon["routes"]) * int(np.prod(
        [len(v) for k, v in canon["grid"].items() if k not in ("mass_kg", "battery_MJ")]))
    if ref is not None:
        fleet = fleet_saving(df, ref, per_cell)
        fleet = fleet[fleet["strategy"] != ref]
        best = best_battery(fleet)
        p = plot_fleet_heatmap(out, fleet, ref)
        if p:
            figs.append((p, f"fleet saving (%) against {ref} over mass x battery, all routes"))
        for p in plot_route_heatmaps(out, df, ref):
            figs.append((p, f"saving (%) against {ref}: {p.stem.removeprefix('saving_heatmap_')}"))
    p = plot_fuel(out, df)
    if p:
        figs.append((p, "corrected fuel per strategy and route"))
    if ref is not None:
        p = plot_distribution(out, df, ref)
        if p:
            figs.append((p, "distribution of savings over routes"))
        p = plot_best_battery(out, best)
        if p:
            figs.append((p, "best battery size per mass"))

    grid_cols = list(canon["grid"]) + [k for k in ("mass_kg", "battery_MJ")
                                      if k not in canon["grid"]]
    n_total = len(canon["routes"]) * len(canon["strategies"]) * int(
        np.prod([len(v) for v in canon["grid"].values()]))
    status = df["status"].value_counts()
    parts = [
        "<!DOCTYPE html><html><head><meta charset='utf-8'>",
        f"<title>jaxems sweep report: {html.escape(out.name)}</title>",
        f"<style>{_CSS}</style></head><body>",
        f"<h1>jaxems sweep report: {html.escape(out.name)}</h1>",
        f"<p class='note'>{len(df)} of {n_total} configurations "
        f"({len(canon['routes'])} routes x "
        f"{' x '.join(f'{len(v)} {k}' for k, v in canon['grid'].items())} x "
        f"{len(canon['strategies'])} strategies); "
        f"status: {html.escape(', '.join(f'{k} {v}' for k, v in status.items()))}. "
        f"Written {time.strftime('%Y-%m-%d %H:%M')}.</p>",
        "<p class='note'>Fuel is corrected for the battery energy left at the end: "
        "F = fuel_J + lambda_b delta_Eb_J (lambda_b &lt; 0). Savings: 100 (F_ref - F) / F_ref "
        "on the same route and grid point" + (f", against <b>{ref}</b>" if ref else "") +
        ". The fleet saving sums the fuel over all routes. Grid parameters other than mass and "
        "battery are averaged over in the figures.</p>",
    ]
    if len(df) < n_total:
        parts.append(f"<p><b>Unfinished sweep:</b> {n_total - len(df)} configurations are "
                     f"missing; rerun <code>jaxems sweep</code> to complete it.</p>")
    parts.append("<h2>Figures</h2>")
    parts += [_img(p, alt) for p, alt in figs]
    parts.append("<h2>Numbers</h2>")
    parts.append(_table(summary_table(df, ref), "per route and strategy (rows: all; means "
                                                "of corrected fuel over the status ok rows)"))
    if best is not None and not best.empty:
        parts.append(_table(best, f"best battery per mass (fleet saving against {ref}; "
                                  f"sufficient: smallest within {SUFFICIENT_PP:g} pp; a mass "
                                  f"with a cell that did not finish is left out)"))
    if fleet is not None and not fleet.empty:
        parts.append(_table(fleet, f"fleet saving against {ref} per mass and battery (blank: "
                                   f"a run of the cell did not finish or is missing, or "
                                   f"{ref} burned no fuel there)"))
    bad = df[df["status"] != "ok"]
    if len(bad):
        parts.append(_table(bad[["route", "strategy", *grid_cols, "status"]],
                            "configurations that did not finish"))
    missed = df[charge_missed(df)]
    parts += _largest(
        missed.assign(delta_Eb_pct=100 * missed["delta_Eb_J"] / (1e6 * missed["battery_MJ"])),
        "delta_Eb_pct", ["route", "strategy", *grid_cols, "delta_Eb_pct", "lambda_b"],
        lambda n, k: f"configurations that end more than {100 * CHARGE_SHARE:g} % of their "
                     f"battery from where they started ({n}; the {k} largest): their corrected "
                     "fuel prices the difference at lambda_b")
    slow = df[trip_long(df)]
    parts += _largest(
        slow.assign(trip_vs_level3_pct=trip_vs_level3_pct(slow["trip_time_s"],
                                                          slow["level3_trip_time_s"])),
        "trip_vs_level3_pct",
        ["route", "strategy", *grid_cols, "trip_time_s", "level3_trip_time_s",
         "trip_vs_level3_pct"],
        lambda n, k: f"configurations whose trip takes more than {100 * TRIP_SHARE:g} % longer "
                     f"than the Level 3 prediction they followed ({n}; the {k} longest)")
    cols = ["route", "strategy", *grid_cols, "fuel_J", "fuel_corrected_J", "fuel_l_per_100km",
            "delta_Eb_J", "lambda_b", "mode_switches", "gear_switches", "trip_time_s",
            "saving_vs_conventional_pct", "saving_vs_baseline_pct", "status"]
    if len(df) <= MAX_FULL_TABLE:
        parts.append(_table(df[cols], "all results"))
    else:
        parts.append(f"<p>{len(df)} rows: the full table is in results.parquet "
                     f"(<code>jaxems.load_sweep(DIR)</code>).</p>")
    parts.append("</body></html>")
    page = out / "report.html"
    atomic_write_bytes(page, "\n".join(parts).encode("utf-8"))
    return page


def _largest(flagged, key: str, cols: list[str], caption) -> list[str]:
    """The page's list of flagged rows (none: no list): the MAX_MISSED of largest |key|, with
    caption(n flagged, k listed)."""
    if not len(flagged):
        return []
    top = flagged.reindex(flagged[key].abs().sort_values(ascending=False).index)
    k = min(len(flagged), MAX_MISSED)
    return [_table(top[cols].head(k), caption(len(flagged), k))]


# -------------------------------------------------------------------------------------- CLI
def cmd_report(args) -> int:
    """`jaxems report DIR`: write report.html and the PNG figures of a sweep directory."""
    page = write_report(args.directory)
    print(page)
    return 0


def register_report(sub) -> None:
    """Add the ``report`` subcommand to an argparse subparsers object (`jaxems.cli`)."""
    p = sub.add_parser("report", help="figures and report.html of a sweep directory",
                       description=cmd_report.__doc__)
    p.add_argument("directory", metavar="DIR", help="a sweep results directory")
    p.set_defaults(func=cmd_report)


def main(argv=None) -> int:
    """``python -m jaxems.report DIR``."""
    import argparse

    from .sweep import SweepError

    ap = argparse.ArgumentParser(prog="python -m jaxems.report", description=cmd_report.__doc__)
    ap.add_argument("directory", metavar="DIR", help="a sweep results directory")
    args = ap.parse_args(argv)
    try:
        return cmd_report(args)
    except (SweepError, ValueError, OSError) as e:
        print(f"jaxems: error: {' '.join(str(e).split())}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    # run the imported module's main, so that what Dask pickles lives in jaxems.report, not __main__
    from jaxems.report import main as _main

    sys.exit(_main())


def plot_run(res, vp, title: str, path: Path, lvl2: dict | None = None) -> None:
    """Five panels over distance (P_d and P_m, mode, gear, E_b, v and v_ref) of a simulated run
    (`jaxems.simulate` Result) to a PNG; `lvl2` adds Level 2's decisions as dashed lines
    (Figures A2-A4 of the paper). The file is written whole or not at all."""
    from .levels.powersplit import MODE_SHORT

    plt = _plt()
    tr = res.trip_trace()
    d = res.as_dict()
    s = tr.s
    pred = res.prediction
    pm = np.asarray(pred.mask)
    fig, ax = plt.subplots(5, 1, figsize=(8, 10), sharex=True)
    ax[0].plot(np.asarray(pred.s)[pm], np.asarray(pred.P_d)[pm] / 1e3, "k:", lw=1.2,
               label="P_d (Level 3)")
    ax[0].plot(s, tr.P_m / 1e3, "C0-", drawstyle="steps-post", label="P_m")
    ax[1].plot(s, tr.mode, "C1-", drawstyle="steps-post", label="mode")
    ax[2].plot(s, tr.gear + 1, "C2-", drawstyle="steps-post", label="gear")
    ax[3].plot(s, tr.E_b / 1e6, "C3-", label="E_b")
    ax[4].plot(s, tr.v * 3.6, "C4-", label="v")
    ax[4].plot(s, tr.v_ref * 3.6, "k--", lw=0.8, label="v_ref (Level 3)")
    if lvl2 is not None:
        kw = dict(ls="--", lw=1.0, alpha=0.8, drawstyle="steps-post")
        ax[0].plot(lvl2["s"], lvl2["P_m"] / 1e3, color="C0", label="P_m (Level 2)", **kw)
        ax[1].plot(lvl2["s"], lvl2["mode"], color="C1", label="mode (Level 2)", **kw)
        ax[2].plot(lvl2["s"], lvl2["gear"], color="C2", label="gear (Level 2)", **kw)
        ax[3].plot(lvl2["s"], lvl2["E_b"] / 1e6, color="C3", ls="--", lw=1.0,
                   label="E_b (Level 2)")
    E_max = float(vp.E_b_max) / 1e6
    for y in (0.0, E_max):
        ax[3].axhline(y, color="0.6", lw=0.6)
    ax[0].set_ylabel("power (kW)")
    ax[1].set_ylabel("mode")
    ax[1].set_yticks(range(4), MODE_SHORT)
    ax[2].set_ylabel("gear")
    ax[3].set_ylabel("E_b (MJ)")
    ax[4].set_ylabel("v (km/h)")
    ax[4].set_xlabel("distance (m)")
    for a in ax:
        a.grid(alpha=0.3)
        a.legend(fontsize=7, loc="best")
    ax[0].set_title(f"{title}: {d['route']}, fuel {d['fuel_J'] / 1e6:.2f} MJ, "
                    f"dE_b {d['delta_Eb_J'] / 1e6:+.2f} MJ, lambda_b {d['lambda_b']:.3f}",
                    fontsize=9)
    fig.tight_layout()
    save_png(fig, path, dpi=110)
