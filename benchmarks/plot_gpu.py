"""Plot multilevel's throughput against the batch on a GPU and on the 2-core CPU (a benchmark
figure for the README's "On a GPU").

    python benchmarks/plot_gpu.py [--gpu docs/bench/gpu/h200/gpu_b*_multilevel.json ...]
        [--cpu docs/bench/scaling.json] [--out docs/bench/gpu/h200/throughput.png]

GPU points: `bench_sweep.py --devices 1 --strategies multilevel --json` runs, one file per
batch (`benchmarks/gpu.sh batch`); the label gives the chunk and the peak device memory. CPU
points: the batch series of `bench_sweep.py --scaling --scaling-strategy multilevel --json`.
"""

from __future__ import annotations

import argparse
import glob
import json
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

GPU_DEFAULT = "docs/bench/gpu/h200/gpu_b*_multilevel.json"


def gpu_points(paths: list[str]) -> list[dict]:
    pts = []
    for path in paths:
        with open(path) as f:
            data = json.load(f)
        run = data["strategies"].get("multilevel")
        if run is None or data.get("precision", "float32") != "float32":
            continue
        pts.append(run)
    return sorted(pts, key=lambda r: r["batch"])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--gpu", nargs="*", default=None)
    ap.add_argument("--cpu", default="docs/bench/scaling.json")
    ap.add_argument("--out", default="docs/bench/gpu/h200/throughput.png")
    args = ap.parse_args(argv)
    gpu = gpu_points(args.gpu if args.gpu else sorted(glob.glob(GPU_DEFAULT)))
    if not gpu:
        raise SystemExit("plot_gpu: no float32 multilevel GPU runs found")
    with open(args.cpu) as f:
        cpu = json.load(f)["scaling"]["multilevel"]["batch"]
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    ax.set_ylim(2, 3000)
    kind = gpu[0].get("device_kind", "GPU")
    ax.loglog([p["batch"] for p in gpu], [p["configs_per_s"] for p in gpu], "o-",
              label=f"{kind}, one device")
    for i, p in enumerate(gpu):  # labels above and below the line in turn
        ax.annotate(f"chunk {p['chunk']}, {p['peak_device_MB'] / 1024:.0f} GB",
                    (p["batch"], p["configs_per_s"]), fontsize=7, textcoords="offset points",
                    xytext=(-20, 8 if i % 2 == 0 else -14))
    ax.loglog([p["batch"] for p in cpu], [p["configs_per_s"] for p in cpu], "s-",
              label=f"2 CPU cores, 2 host devices, chunks of {cpu[0].get('chunk', '?')}")
    ax.axhline(200, color="grey", ls=":", label="target: 200 configurations/s")
    ax.set_xlabel("batch (configurations)")
    ax.set_ylabel("configurations / s")
    ax.set_title("multilevel on LongHaul (108 km), float32")
    ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=120)
    print(f"wrote {args.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    from jaxems.cli import script_main

    raise SystemExit(script_main("plot_gpu", main))
