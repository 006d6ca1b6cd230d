"""Figures 7, 8 and 9 of the paper: H* and P_b* over lambda_b, and the control map of the
optimal mode over (lambda_b, P_d) with the guards B1..B5, for one gear and speed.

    python experiments/control_map.py [--out DIR] [--speed-kmh 83] [--gear 12] [--pd-kw 100]
                                      [--json]

Writes fig7_hamiltonian.png, fig8_battery_power.png and fig9_control_map.png into DIR
(default experiments/out). The map is computed with the exact kernel (`mode_gear_split`,
limits included); the guards are the closed forms of `powersplit.guards`, drawn where they
apply. With --json, prints the guard values at the chosen speed as one JSON object.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.colors import ListedColormap  # noqa: E402

from jaxems import powertrain as pt  # noqa: E402
from jaxems.levels import powersplit as ps  # noqa: E402
from jaxems.cli import number, positive_float, whole_number  # noqa: E402
from jaxems.params import KMH, RPM, load_vehicle  # noqa: E402

COLORS = {ps.MC: "tab:purple", ps.ME: "tab:red", ps.MM: "tab:green", ps.MO: "0.8"}
NAMES = {
    ps.MC: "M_c combined",
    ps.ME: "M_e engine-only",
    ps.MM: "M_m motor-only",
    ps.MO: "M_o open",
}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="experiments/out")
    ap.add_argument("--vehicle", default="reference_truck")
    ap.add_argument("--speed-kmh", type=positive_float, default=83.0)
    ap.add_argument("--gear", type=whole_number, default=12, help="gear number 1..12")
    ap.add_argument("--pd-kw", type=number, default=100.0, help="P_d# of Figures 7 and 8")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    vp = load_vehicle(a.vehicle)
    n_gears = int(vp.gear_ratio.shape[0])
    if not 1 <= a.gear <= n_gears:
        raise ValueError(f"--gear: a gear number from 1 to {n_gears} (got {a.gear})")
    g = a.gear - 1
    v = a.speed_kmh * KMH
    w = float(vp.gear_ratio[g] * vp.r_d * v)
    lams = np.linspace(-3.0, -1.5, 301)
    pds = np.linspace(-150e3, 300e3, 301)

    split = jax.jit(
        jax.vmap(jax.vmap(ps.mode_gear_split, (None, 0, None, None)), (None, None, None, 0))
    )
    s = split(vp, jnp.asarray(pds), v, jnp.asarray(lams))  # (L, P, 4, G)
    H = np.asarray(s.H)[:, :, :, g]
    best = np.where(np.isfinite(H).any(-1), np.argmin(H, -1), -1)  # (L, P)
    gd = ps.guards(vp, w, jnp.asarray(lams))
    B1, B2 = float(gd.B1), float(gd.B2)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)

    # Figure 9: control map
    fig, ax = plt.subplots(figsize=(7, 5))
    cmap = ListedColormap([COLORS[m] for m in range(4)])
    ax.pcolormesh(lams, pds / 1e3, best.T, cmap=cmap, vmin=-0.5, vmax=3.5, shading="auto")
    ax.axvline(B1, color="k", ls="--", lw=1)
    ax.axvline(B2, color="k", ls="--", lw=1)
    ax.text(B1, pds[-1] / 1e3, " B1", va="top")
    ax.text(B2, pds[-1] / 1e3, " B2", va="top")
    for name, sel in (("B3", lams > B1), ("B4", (lams > B2) & (lams < B1)), ("B5", lams < B2)):
        y = np.asarray(getattr(gd, name)) / 1e3
        ax.plot(lams[sel], y[sel], "k-", lw=1.5)
        i = int(np.flatnonzero(sel)[len(np.flatnonzero(sel)) // 2])
        ax.text(lams[i], y[i], f" {name}", va="bottom")
    m_lim = float(pt.motor_power_limit(vp, w)) / 1e3
    ax.axhline(m_lim, color="k", ls=":", lw=1)
    ax.text(lams[0], m_lim, " motor power limit", va="bottom", fontsize=8)
    for m in range(4):
        ax.plot([], [], "s", color=COLORS[m], label=NAMES[m])
    ax.set_xlabel("lambda_b [-]")
    ax.set_ylabel("P_d [kW]")
    ax.set_title(f"Optimal mode, gear {a.gear} at {a.speed_kmh:g} km/h ({w / RPM:.0f} rpm)")
    ax.legend(loc="lower left", fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "fig9_control_map.png", dpi=120)
    plt.close(fig)

    # Figures 7 and 8: cross-section at P_d#
    s1 = jax.jit(jax.vmap(ps.mode_gear_split, (None, None, None, 0)))(
        vp, a.pd_kw * 1e3, v, jnp.asarray(lams)
    )
    H1 = np.asarray(s1.H)[:, :, g]
    Pb1 = np.asarray(s1.P_b)[:, :, g]
    for fname, Y, ylabel, scale in (
        ("fig7_hamiltonian.png", H1, "H_1 [kW]", 1e3),
        ("fig8_battery_power.png", Pb1, "P_b* [kW]", 1e3),
    ):
        fig, ax = plt.subplots(figsize=(7, 4))
        for m in (ps.MM, ps.MC, ps.ME):
            ax.plot(lams, Y[:, m] / scale, color=COLORS[m], label=NAMES[m])
        if fname.startswith("fig7"):
            ax.plot(lams, np.nanmin(H1[:, :3], 1) / scale, "k:", lw=2, label="H_1*")
        for b, nm in ((B1, "B1"), (B2, "B2")):
            ax.axvline(b, color="k", ls="--", lw=1)
            ax.text(b, ax.get_ylim()[1], f" {nm}", va="top")
        ax.set_xlabel("lambda_b [-]")
        ax.set_ylabel(ylabel)
        ax.set_title(f"P_d# = {a.pd_kw:g} kW, gear {a.gear}, {a.speed_kmh:g} km/h")
        ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(out / fname, dpi=120)
        plt.close(fig)

    lam_ref = -2.0
    gr = ps.guards(vp, w, lam_ref)
    info = {
        "speed_kmh": a.speed_kmh,
        "gear": a.gear,
        "w_rpm": w / RPM,
        "B1": B1,
        "B2": B2,
        "at_lambda_b": lam_ref,
        "B3_kW": float(gr.B3) / 1e3,
        "B4_kW": float(gr.B4) / 1e3,
        "B5_kW_at_-2.6": float(ps.guards(vp, w, -2.6).B5) / 1e3,
        "motor_limit_kW": m_lim,
        "files": sorted(str(p) for p in out.glob("fig*.png")),
    }
    if a.json:
        print(json.dumps(info))
    else:
        for k, val in info.items():
            print(f"{k}: {val}")
    return 0


if __name__ == "__main__":
    from jaxems.cli import script_main

    raise SystemExit(script_main("control_map", main))
