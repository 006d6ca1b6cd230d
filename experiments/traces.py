"""Figures A2-A4 of the paper: decisions and results over the short track, 25 t.

- figA2.png: the multilevel iteration scheme after iteration 0 (``multilevel``, n_iter = 1);
- figA3.png: after iteration 1 (``multilevel``, n_iter = 2);
- figA4.png: the multilevel MPC (``multilevel-mpc``, Level 1 horizon 5 samples of 1 s).

Each figure has five panels over distance: the demanded power at the wheels P_d and the motor
power P_m (kW), the mode, the gear, the battery energy E_b (MJ) and the speed v with the
Level 3 reference speed. Solid lines are the plant's run of the strategy (Level 1's decisions
with open driveline at switches); dashed lines are Level 2's decisions at its charge-sustaining
costate with the engine speed of iteration 0 (1100 rpm), as in the paper's Figures A2 and A4
(Appendix E: the MPC's Level 2 sees the whole 1055 m track, so its traces equal those of A2).
Figure A3 shows no Level 2 lines: its Level 2 uses iteration 0's gears, which `simulate` does
not return.

    .venv/bin/python experiments/traces.py [--out out] [--figures A2,A3,A4] [--mass 25000]

Prints one line per figure (fuel, battery balance, lambda_b, switches) and the files written.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from jax import config

config.update("jax_enable_x64", True)

from jaxems.cli import comma_list, number  # noqa: E402
from jaxems.levels import battery as l2  # noqa: E402
from jaxems.params import load_vehicle, with_overrides  # noqa: E402
from jaxems.report import plot_run  # noqa: E402
from jaxems.strategies import simulate  # noqa: E402

# figure -> (strategy, options, title)
FIGURES = {
    "A2": ("multilevel", {"n_iter": 1}, "multilevel iteration 0", True),
    "A3": ("multilevel", {"n_iter": 2}, "multilevel iteration 1", False),
    "A4": ("multilevel-mpc", {}, "multilevel MPC (Level 1 horizon 5 s)", True),
}


def level2_traces(vp, pred) -> dict:
    """Level 2 of iteration 0 on the Level 3 prediction: per valid step (T',) s (m), P_m (W),
    mode, gear (1-based), and E_b (J) at the step starts; lambda_b (first value)."""
    m = np.asarray(pred.mask)
    P_d, v = np.asarray(pred.P_d), np.asarray(pred.v)
    w = np.full_like(v, float(vp.w_pred))
    dt = float(pred.dt)
    c = l2.solve_costate(vp, P_d, v, w, m, dt)
    gear, ok = l2.select_gears(vp, P_d, v, w, m)
    st = l2.level2_steps(vp, P_d, v, gear, ok, c.lam, dt)
    return {"s": np.asarray(pred.s)[m], "P_m": np.asarray(st.P_m)[m],
            "mode": np.asarray(st.mode)[m], "gear": np.asarray(gear)[m] + 1,
            "E_b": np.asarray(c.E_b)[:-1][m], "lambda_b": float(c.lam0)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("out"), help="output folder (out/)")
    ap.add_argument("--figures", default="A2,A3,A4", help="comma-separated: A2, A3, A4")
    ap.add_argument("--route", default="short_track", help="route file or bundled name")
    ap.add_argument("--mass", type=number, default=25000.0, help="vehicle mass in kg (25000)")
    args = ap.parse_args(argv)
    figs = [f.upper() for f in comma_list(args.figures, "--figures")]
    bad = [f for f in figs if f not in FIGURES]
    if bad:
        print(f"traces: error: unknown figure(s) {', '.join(bad)} (A2, A3, A4)", file=sys.stderr)
        return 1
    try:
        vp = with_overrides(load_vehicle("reference_truck"), mass_kg=args.mass)
        args.out.mkdir(parents=True, exist_ok=True)
        for f in figs:
            strategy, opts, title, with_l2 = FIGURES[f]
            res = simulate(args.route, vp, strategy, **opts)
            lvl2 = level2_traces(vp, res.prediction) if with_l2 else None
            path = args.out / f"fig{f}.png"
            plot_run(res, vp, title, path, lvl2)
            d = res.as_dict()
            l2_text = f", Level 2 lambda_b {lvl2['lambda_b']:.3f}" if lvl2 else ""
            print(f"{f}: {title}: fuel {d['fuel_J'] / 1e6:.3f} MJ, dE_b "
                  f"{d['delta_Eb_J'] / 1e6:+.3f} MJ, lambda_b {d['lambda_b']:.3f}{l2_text}, "
                  f"switches {d['mode_switches']} mode / {d['gear_switches']} gear -> {path}")
    except (ValueError, OSError) as e:
        print(f"traces: error: {' '.join(str(e).split())}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    from jaxems.cli import script_main

    sys.exit(script_main("traces", main))
