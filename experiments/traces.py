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

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from jax import config  # noqa: E402

config.update("jax_enable_x64", True)

from jaxems.levels import battery as l2  # noqa: E402
from jaxems.params import load_vehicle, with_overrides  # noqa: E402
from jaxems.strategies import simulate  # noqa: E402

# figure -> (strategy, options, title)
FIGURES = {
    "A2": ("multilevel", {"n_iter": 1}, "multilevel iteration 0", True),
    "A3": ("multilevel", {"n_iter": 2}, "multilevel iteration 1", False),
    "A4": ("multilevel-mpc", {}, "multilevel MPC (Level 1 horizon 5 s)", True),
}
MODE_NAMES = ["Mc", "Me", "Mm", "Mo"]


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


def plot_run(res, vp, title: str, path: Path, lvl2: dict | None = None) -> None:
    """Five panels over distance (P_d and P_m, mode, gear, E_b, v and v_ref) to a PNG."""
    tr = res.trace
    d = res.as_dict()
    live = np.asarray(tr.t) < d["trip_time_s"]
    g = lambda x: np.asarray(x)[live]  # noqa: E731
    s = g(tr.s)
    pred = res.prediction
    pm = np.asarray(pred.mask)
    fig, ax = plt.subplots(5, 1, figsize=(8, 10), sharex=True)
    ax[0].plot(np.asarray(pred.s)[pm], np.asarray(pred.P_d)[pm] / 1e3, "k:", lw=1.2,
               label="P_d (Level 3)")
    ax[0].plot(s, g(tr.P_m) / 1e3, "C0-", drawstyle="steps-post", label="P_m")
    ax[1].plot(s, g(tr.mode), "C1-", drawstyle="steps-post", label="mode")
    ax[2].plot(s, g(tr.gear) + 1, "C2-", drawstyle="steps-post", label="gear")
    ax[3].plot(s, g(tr.E_b) / 1e6, "C3-", label="E_b")
    ax[4].plot(s, g(tr.v) * 3.6, "C4-", label="v")
    ax[4].plot(s, g(tr.v_ref) * 3.6, "k--", lw=0.8, label="v_ref (Level 3)")
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
    ax[1].set_yticks(range(4), MODE_NAMES)
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
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("out"), help="output folder (out/)")
    ap.add_argument("--figures", default="A2,A3,A4", help="comma-separated: A2, A3, A4")
    ap.add_argument("--route", default="short_track", help="route file or bundled name")
    ap.add_argument("--mass", type=float, default=25000.0, help="vehicle mass in kg (25000)")
    args = ap.parse_args(argv)
    figs = [f.strip().upper() for f in args.figures.split(",") if f.strip()]
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
    sys.exit(main())
