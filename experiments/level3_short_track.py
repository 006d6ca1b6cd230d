"""Level 3 on the paper's short test track (section 7.1, Appendix D.1): P_d on each slope.

The paper's Level 3 cruises at 25 km/h with a 25 t truck and reports P_d = +113, -192, +215,
-90 kW on the +6, -12, +12, -6 % slopes (about 11 kW on the flat). Pure road load at 25 km/h
gives 110, -195, 211, -94 kW with the parameters of Table 3.

    python experiments/level3_short_track.py [--json] [--route PATH] [--mass KG]

The slope value is the mean P_d over the time steps that lie wholly on the slope. With --json,
prints one object {"segments": [{"slope_pct": .., "P_d_kW": ..}, ...]} in route order.
"""

from __future__ import annotations

import argparse
import json
import sys

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from jaxems.cli import positive_float  # noqa: E402
from jaxems.io import load_route  # noqa: E402
from jaxems.levels.velocity import predict_velocity  # noqa: E402
from jaxems.params import KMH, load_vehicle  # noqa: E402

PAPER_KW = {6.0: 113.0, -12.0: -192.0, 12.0: 215.0, -6.0: -90.0}


def slope_segments(pred) -> tuple[list[dict], float]:
    """Mean P_d (kW) over the steps wholly on each slope, in route order, and on the flat."""
    m = np.asarray(pred.mask)
    g = np.round(np.asarray(pred.grade)[m] * 100.0, 6)  # %; steps across a change get odd values
    P = np.asarray(pred.P_d)[m] / 1e3
    segments: list[dict] = []
    k = 0
    while k < len(g):
        j = k
        while j + 1 < len(g) and g[j + 1] == g[k]:
            j += 1
        on_slope = g[k] != 0 and (j - k + 1) >= 3  # a run of steps at one gradient
        if on_slope:
            segments.append({"slope_pct": float(g[k]), "P_d_kW": float(P[k : j + 1].mean())})
        k = j + 1
    flat = P[g == 0]
    return segments, float(flat.mean()) if flat.size else float("nan")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    ap.add_argument("--route", default="short_track", help="route file or bundled name")
    ap.add_argument("--mass", type=positive_float, default=25000.0, help="vehicle mass (kg)")
    args = ap.parse_args(argv)
    vp = load_vehicle().replace(mass=args.mass, v_cruise=25.0 * KMH)
    route = load_route(args.route)
    pred = predict_velocity(route, vp)
    segments, flat = slope_segments(pred)
    if args.json:
        print(json.dumps({"segments": segments}))
        return 0
    v = 25.0 * KMH
    print(
        f"Level 3 on {args.route}: {args.mass / 1000:g} t at 25 km/h, "
        f"w_pred = {float(vp.w_pred) * 60 / (2 * np.pi):.0f} rpm"
    )
    print(f"{'slope %':>8} {'P_d kW':>8} {'paper kW':>9} {'dev %':>6} {'road load kW':>13}")
    for seg in segments:
        slope = seg["slope_pct"]
        alpha = np.arctan(slope / 100)
        f0 = 0.5 * vp.c_w * vp.area * vp.rho * v * v + vp.mass * vp.g * (
            vp.c_r * np.cos(alpha) + np.sin(alpha)
        )
        paper = PAPER_KW.get(slope, float("nan"))
        dev = (seg["P_d_kW"] - paper) / abs(paper) * 100
        print(
            f"{slope:>+8.1f} {seg['P_d_kW']:>+8.1f} {paper:>+9.0f} {dev:>+6.1f} "
            f"{float(f0 * v) / 1e3:>+13.1f}"
        )
    print(f"{'flat':>8} {flat:>+8.1f} {11.0:>+9.0f}")
    print(f"trip time {float(pred.trip_time):.1f} s, feasible: {bool(pred.feasible)}")
    return 0


if __name__ == "__main__":
    from jaxems.cli import script_main

    raise SystemExit(script_main("level3_short_track", main))
