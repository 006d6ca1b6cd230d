"""Figures 12-15 of the paper on a synthetic route: E_b(t_f) jumps over lambda_b; I2a / I2b.

Route: 2000 s at a constant 60 km/h over piecewise-constant grades (SEGMENTS), reference truck,
omega = 1100 rpm (Level 2 iteration 0). Constant speed
keeps one gear, so every step crosses the guards B1 and B2 at the same lambda_b and E_b(t_f)
jumps by megajoules there (Figure 12). At the charge-sustaining costate (on a guard), the two
trajectories B+ and B- just below and above it are mixed with the ratio r of eq. 55 (I2a) and
switched with the fewest switches (I2b, Figures 13-15): without limits, and within the narrowest
band E_b(0) +- (0.25, 0.5, 1, 2, 4) E_b_max in which switching alone keeps E_b (on this route
the flat stretches drain the battery on both sides of the guard, so switching alone cannot hold
the real limits and I1 has to split). The bottom panel is the full Level 2 answer with the
battery limits (I1 pieces, I2b inside the pieces at a guard).

    .venv/bin/python experiments/costate_jumps.py [--out DIR]

Writes costate_jumps_fig12.png, costate_jumps_fig13.png and prints the numbers.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from jax import config  # noqa: E402

config.update("jax_enable_x64", True)

from jaxems import powertrain as pt  # noqa: E402
from jaxems.levels import battery as b  # noqa: E402
from jaxems.params import RPM, load_vehicle  # noqa: E402

SEGMENTS = [(400, 0.008), (200, -0.01), (400, 0.012), (200, -0.015), (400, 0.008), (400, 0.0)]


def route(vp, dt=2.0):
    """2000 s at 60 km/h over piecewise-constant grades (s, rise over run) -> P_d, v, t."""
    grade = np.concatenate([np.full(int(n / dt), g) for n, g in SEGMENTS])
    T = len(grade)
    v = np.full(T, 60 / 3.6)
    return np.asarray(pt.road_load(vp, v, grade)) * v, v, np.arange(T) * dt


def main(out: Path) -> None:
    vp = load_vehicle()
    dt = 2.0
    P_d, v, t = route(vp, dt=dt)
    T = len(t)
    w = np.full(T, 1100 * RPM)
    mask = np.ones(T, bool)
    E0 = float(vp.E_b0)
    gear, ok = b.select_gears(vp, P_d, v, w, mask)

    # Figure 12: E_b(t_f) - E_b(0) over a sweep of constant lambda_b
    lams = np.linspace(-3.0, -1.6, 561)
    steps = b.jax.jit(b.level2_steps)
    dEf = np.array([float(np.sum(steps(vp, P_d, v, gear, ok, lam, dt).dE)) for lam in lams])
    jumps = np.where(np.abs(np.diff(dEf)) > 0.25 * float(vp.E_b_max))[0]
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.plot(lams, dEf / 1e6, ".-", ms=2)
    ax.axhline(0, color="k", lw=0.8)
    ax.set_xlabel("lambda_b (-)")
    ax.set_ylabel("E_b(t_f) - E_b(0) (MJ)")
    ax.set_title("Charge sustenance over a constant costate (cf. Figure 12)")
    for j in jumps:
        ax.axvline(0.5 * (lams[j] + lams[j + 1]), color="r", ls=":", lw=0.8)
    fig.tight_layout()
    fig.savefig(out / "costate_jumps_fig12.png", dpi=120)
    plt.close(fig)

    # the charge-sustaining solution without limits: on a guard -> I2a and I2b
    r = b.bisect_costate(vp, P_d, v, w, mask, dt)
    lam = float(r.lam0)
    e_plus = E0 + float(np.sum(r.dE_plus))
    e_minus = E0 + float(np.sum(r.dE_minus))
    rp = float(r.r_plus[0])
    E_plus = E0 + np.concatenate([[0.0], np.cumsum(np.asarray(r.dE_plus))])
    E_minus = E0 + np.concatenate([[0.0], np.cumsum(np.asarray(r.dE_minus))])
    E_i2a = np.asarray(r.E_b_i2a)
    # I2b within the widest band around E0 in which B+ / B- can still be switched (Figs 14-15)
    sw = None
    for frac in (0.25, 0.5, 1.0, 2.0, 4.0):
        E_lo, E_hi = E0 - frac * float(vp.E_b_max), E0 + frac * float(vp.E_b_max)
        sw = b.minimal_switching(r.dE_plus, r.dE_minus, E0, E0, E_lo, E_hi, 1.0)
        if bool(sw.feasible):
            break
    sw_free = b.minimal_switching(r.dE_plus, r.dE_minus, E0, E0, -np.inf, np.inf, 1.0)
    full = b.solve_costate(vp, P_d, v, w, mask, dt)
    P_m_plus = np.asarray(steps(vp, P_d, v, gear, ok, float(r.lam_lo[0]), dt).P_m)
    P_m_minus = np.asarray(steps(vp, P_d, v, gear, ok, float(r.lam_hi[0]), dt).P_m)

    tt = np.concatenate([[0.0], t + dt])
    fig, (a0, a1, a2) = plt.subplots(3, 1, figsize=(8, 8), sharex=True)
    a0.plot(t, P_d / 1e3, "k", lw=0.8, label="P_d")
    a0.plot(t, P_m_plus / 1e3, "-.", label="P_m on B+")
    a0.plot(t, P_m_minus / 1e3, "--", label="P_m on B-")
    a0.set_ylabel("power (kW)")
    a0.legend(loc="upper right", fontsize=8)
    a0.set_title(f"On the guard lambda_b = {lam:.4f} (cf. Figures 13-15)")
    a1.plot(tt, E_plus / 1e6, "-.", label="B+")
    a1.plot(tt, E_minus / 1e6, "--", label="B-")
    a1.plot(tt, E_i2a / 1e6, ":", lw=2, label=f"I2a, r(B-) = {1 - rp:.2f}")
    a1.plot(tt, np.asarray(sw_free.E_b) / 1e6, label=f"I2b, {int(sw_free.n_switches)} switch")
    a1.axhline(E0 / 1e6, color="k", lw=0.6)
    a1.set_ylabel("E_b (MJ)")
    a1.legend(loc="upper left", fontsize=8)
    a1.plot(tt, np.asarray(sw.E_b) / 1e6, lw=0.8,
            label=f"I2b in [{E_lo / 1e6:.0f}, {E_hi / 1e6:.0f}] MJ, {int(sw.n_switches)} sw.")
    a2.plot(tt, np.asarray(full.E_b) / 1e6,
            label=f"with limits: {int(full.n_pieces)} pieces, {int(full.n_switches)} switches")
    for lim in (0.0, float(vp.E_b_max)):
        a2.axhline(lim / 1e6, color="r", lw=0.8)
    a2b = a2.twinx()
    a2b.plot(t, np.asarray(full.lam), "g", lw=0.8)
    a2b.set_ylabel("lambda_b (-)", color="g")
    a2.set_ylabel("E_b (MJ)")
    a2.set_xlabel("time (s)")
    a2.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "costate_jumps_fig13.png", dpi=120)
    plt.close(fig)

    print(f"route: {T} steps of {dt} s, gear(s) {sorted(set(np.asarray(gear).tolist()))}")
    print("jumps of E_b(t_f) at lambda_b ~ "
          + ", ".join(f"{0.5 * (lams[j] + lams[j + 1]):.3f}" for j in jumps))
    print(f"charge-sustaining costate {lam:.5f}, status {b.status_names(r.status)}")
    print(f"E_b(t_f) - E_b(0): B+ {(e_plus - E0) / 1e6:+.3f} MJ, B- {(e_minus - E0) / 1e6:+.3f} MJ")
    print(f"I2a: r(B-) = {1 - rp:.3f}, end error {(E_i2a[-1] - E0):.1f} J, "
          f"fuel {float(r.fuel) / 1e6:.3f} MJ")
    f_sw = float(np.sum(np.asarray(sw.sel) * np.asarray(r.E_f_plus)
                        + (1 - np.asarray(sw.sel)) * np.asarray(r.E_f_minus)))
    print(f"I2b without limits: {int(sw_free.n_switches)} switch(es); in the band "
          f"[{E_lo / 1e6:.2f}, {E_hi / 1e6:.2f}] MJ: {int(sw.n_switches)} switches, "
          f"feasible {bool(sw.feasible)}, end error {float(sw.E_b[-1]) - E0:.1f} J, "
          f"fuel {f_sw / 1e6:.3f} MJ")
    print(f"with limits [0, {float(vp.E_b_max) / 1e6:.0f}] MJ: {int(full.n_pieces)} pieces, "
          f"costates {np.round(np.asarray(full.lam_pieces)[: int(full.n_pieces)], 4).tolist()}, "
          f"status {b.status_names(full.status)}, E_b in [{float(full.E_b.min()) / 1e6:.3f}, "
          f"{float(full.E_b.max()) / 1e6:.3f}] MJ, fuel {float(full.fuel) / 1e6:.3f} MJ")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("experiments/out"))
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    main(args.out)
