"""Plot the scaling figures of `bench_sweep.py --scaling --json` (time vs route length and
batch size, log-log, with a linear reference through the first point).

    python benchmarks/bench_sweep.py --scaling --json > docs/bench/scaling.json
    python benchmarks/plot_scaling.py [docs/bench/scaling.json] [--out docs/bench/scaling.png]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.ticker import NullFormatter, ScalarFormatter  # noqa: E402


def _panel(ax, runs: dict, key: str, xlabel: str, xval, title: str):
    """One log-log panel: median wall time per call against xval(point), each strategy with
    its linear reference through its first point; labels give each run's peak RSS."""
    xs: set[float] = set()
    for name, sc in runs.items():
        pts = sc[key]
        if not pts:
            continue
        x = np.array([xval(p) for p in pts], float)
        t = np.array([p["median_s"] for p in pts], float)
        (line,) = ax.loglog(x, t, "o-", label=f"{name} (chunk {pts[0]['chunk']})")
        ax.loglog(x, t[0] * x / x[0], ":", color=line.get_color(), alpha=0.7,
                  label=f"{name}: linear from first point")
        for xi, ti, p in zip(x, t, pts, strict=True):  # peak memory of each run
            ax.annotate(f"{p['peak_rss_MB'] / 1024:.1f} GB", (xi, ti), fontsize=6,
                        textcoords="offset points", xytext=(4, -9), color=line.get_color())
        xs.update(x.tolist())
    ax.set_xticks(sorted(xs))
    ax.xaxis.set_major_formatter(ScalarFormatter())
    ax.xaxis.set_minor_formatter(NullFormatter())
    ax.yaxis.set_major_formatter(ScalarFormatter())
    # minor labels only where the panel spans less than a decade (else they overlap)
    lo, hi = ax.get_ylim()
    ax.yaxis.set_minor_formatter(ScalarFormatter() if hi / lo < 10 else NullFormatter())
    ax.set_xlabel(xlabel)
    ax.set_ylabel("wall time per call (s, median; labels: peak RSS)")
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)


def plot(data: dict, out: Path) -> Path:
    """Write the two-panel figure of a `bench_sweep.py --scaling` JSON object to `out`."""
    runs = data["scaling"]
    first = next(iter(runs.values()))
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.4))
    b = first["length"][0]["batch"] if first["length"] else "?"
    _panel(axes[0], runs, "length", "route length (km)", lambda p: p["length_m"] / 1e3,
           f"{data['route']} tiled 1x, 2x, 4x; batch {b}")
    _panel(axes[1], runs, "batch", "batch size (configurations)", lambda p: p["batch"],
           f"{data['route']}; batch size")
    p0 = (first["batch"] or first["length"])[0]
    fig.suptitle(f"jaxems fleet scaling: {data['precision']}, {p0['devices']} host device(s), "
                 f"{data['machine']['cpu_count']} CPU cores (shared), commit "
                 f"{data.get('code', {}).get('commit', '?')}",
                 fontsize=10)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=120)
    plt.close(fig)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("json_file", nargs="?", default="docs/bench/scaling.json")
    ap.add_argument("--out", default=None, help="PNG path (default: the JSON's path with .png)")
    args = ap.parse_args(argv)
    src = Path(args.json_file)
    data = json.loads(src.read_text())
    if "scaling" not in data:
        ap.error(f"{src}: no 'scaling' entry (run bench_sweep.py --scaling --json)")
    out = Path(args.out) if args.out else src.with_suffix(".png")
    print(plot(data, out))
    return 0


if __name__ == "__main__":
    from jaxems.cli import script_main

    raise SystemExit(script_main("plot_scaling", main))
