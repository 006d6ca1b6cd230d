"""Where the MPC's fuel goes against the iteration's: Level 1's horizon and Level 2's costate.

The MPC (`multilevel-mpc`) differs from the iteration (`multilevel`) in two places: Level 1
sees h1 samples ahead (5 s, the paper's) instead of the whole route, and its costate comes
from Level 2 every second on a 1000 s window from the measured E_b (omega at 1100 rpm, no
Level 1 gear fed back) instead of the iteration's plan-keeping Level 1. This script separates
the two: besides both strategies, it runs the MPC at each h1 of `--h1`, and the MPC's own
Level 1 (`strategies.mpc_level1`, the same DP from the measured mode and gear, the plant
splitting the power at the costate) fed the iteration's costate trace instead of Level 2's,
looked up at the plant's position (no Level 2). Corrected fuel J + lambda_b delta E_b, each
run priced at its own first costate. Float64; one vehicle, half charge.

    .venv/bin/python experiments/mpc_gap.py [--route RegionalDelivery] [--mass 20000]
        [--h1 5,20] [--json]

`--json` prints one JSON object ``{"rows": [...]}`` on stdout; progress goes to stderr.
"""

from __future__ import annotations

import argparse
import sys
import time

import jax
from jax import config

config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from jaxems import strategies as S  # noqa: E402
from jaxems import switching as sw  # noqa: E402
from jaxems.cli import comma_list, number, print_result  # noqa: E402
from jaxems.params import check_vehicle, load_vehicle, with_overrides  # noqa: E402

FIELDS = ("fuel_J", "fuel_corrected_J", "delta_Eb_J", "lambda_b", "trip_time_s",
          "mode_switches", "gear_switches")


def _row(run: str, h1, fields: dict) -> dict:
    out = {"run": run, "h1_s": h1}
    for k in FIELDS:
        v = np.asarray(fields[k]).reshape(-1)[0]
        out[k] = int(v) if k.endswith("switches") else float(v)
    return out


def given_costate(route, vp, s, lam, h1: int) -> dict:
    """The MPC's Level 1 over h1 samples at the costate lam (T,) given by position s (T,) m,
    in the MPC's plant loop (no Level 2): `Result` fields of the run."""
    opts = S.resolve_options(S.make_options(h1=h1), vp)
    params = sw.checked_params(None, np.asarray(vp.mass).dtype)
    n_steps = S.steps_for_batch(route, vp, 1.0, "multilevel-mpc", opts)
    s, lam = jnp.asarray(s), jnp.asarray(lam)

    def ctrl(p, cstate, vp_, obs):
        at = jnp.interp(obs.s, s, lam).astype(p.P_d.dtype)
        return cstate, S.mpc_level1(p, vp_, obs, at, h1)

    run = jax.jit(lambda r, v: S.run_multilevel_mpc(r, v, 1.0, n_steps, opts, params,
                                                    ctrl=ctrl))(route, vp)
    return S._fields(run.metrics, vp)


def gap_rows(route_name: str, mass: float, h1s: list[int]) -> list[dict]:
    """The iteration, the MPC at each h1, and the MPC's Level 1 at the iteration's costate at
    each h1; each row with its corrected fuel's gap against the iteration (%)."""
    vp = check_vehicle(with_overrides(load_vehicle("reference_truck"), mass_kg=mass))
    route = S.route_arg(route_name)
    it = S.simulate(route, vp, "multilevel")
    rows = [_row("multilevel", None, it.fields)]
    for h1 in h1s:
        t0 = time.perf_counter()
        rows.append(_row("multilevel-mpc", h1,
                         S.simulate(route, vp, "multilevel-mpc", h1=h1).fields))
        rows.append(_row("mpc Level 1 at the iteration's costate", h1,
                         given_costate(route, vp, it.trace.s, it.trace.lam, h1)))
        print(f"h1 = {h1} s: {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    base = rows[0]["fuel_corrected_J"]
    for r in rows:
        r["gap_pct"] = 100 * (r["fuel_corrected_J"] / base - 1)
    return rows


def horizons(text: str) -> list[int]:
    """--h1's horizons: whole numbers >= 1, else ValueError naming the option."""
    try:
        h1s = [int(x) for x in comma_list(text)]
    except ValueError:
        h1s = []
    if not h1s or min(h1s) < 1:
        raise ValueError(f"--h1: expected comma-separated whole numbers >= 1 (got {text!r})")
    return h1s


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--route", default="RegionalDelivery")
    ap.add_argument("--mass", type=number, default=20000.0)
    ap.add_argument("--h1", default="5,20", help="Level 1 horizons (samples), comma-separated")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)

    def fmt(out):
        lines = [f"{a.route}, reference_truck, {a.mass:.0f} kg, float64 (corrected fuel "
                 "against the iteration's)",
                 f"{'run':40s} {'h1 [s]':>6s} {'J corr [MJ]':>11s} {'gap %':>6s} "
                 f"{'dE_b [MJ]':>9s} {'trip [s]':>8s} {'switches M/G':>12s}"]
        for r in out["rows"]:
            h1 = "-" if r["h1_s"] is None else str(r["h1_s"])
            lines.append(f"{r['run']:40s} {h1:>6s} {r['fuel_corrected_J'] / 1e6:11.3f} "
                         f"{r['gap_pct']:+6.2f} {r['delta_Eb_J'] / 1e6:+9.3f} "
                         f"{r['trip_time_s']:8.0f} {r['mode_switches']:>7d}/{r['gear_switches']}")
        return "\n".join(lines)

    return print_result("mpc_gap.py", lambda: {"route": a.route, "mass_kg": a.mass,
                                               "rows": gap_rows(a.route, a.mass,
                                                                horizons(a.h1))},
                        a.json, fmt)


if __name__ == "__main__":
    sys.exit(main())
