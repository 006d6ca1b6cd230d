"""Table A2 of the paper: equivalent cost of the time lost by a 1 s open driveline (App. C.2).

The truck (25 t, the paper's short-cycle mass) cruises at 25 km/h on 0, 6 and 12 % slopes; the
driveline opens for 1 s, then the speed is recovered with the largest driveline force of the
mode after the switch (default engine-only, best gear); lambda_t = -25 kJ/s.

    python experiments/table_a2.py [--json] [--mass KG] [--speed-kmh 25] [--mode Me|Mc|Mm]
                                   [--lambda-t -25000] [--tau 1]

With --json prints {"rows": [{"slope_pct": .., "speed_loss_mps": .., "time_loss_s": ..,
"cost_kJ": .., "F0_N": .., "F_max_N": .., "saturated": ..}, ...]}. Losses are magnitudes
(the paper prints them negative).
"""

from __future__ import annotations

import argparse
import json

import jax

jax.config.update("jax_enable_x64", True)

from jaxems.cli import number, positive_float  # noqa: E402
from jaxems.levels.powersplit import MODE_SHORT  # noqa: E402
from jaxems.params import KMH, load_vehicle  # noqa: E402
from jaxems.switching import SwitchCostParams, table_a2  # noqa: E402

PAPER = {0.0: (0.075, 0.01, 0.17), 6.0: (0.65, 0.07, 1.8), 12.0: (1.25, 0.22, 5.6)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    ap.add_argument("--vehicle", default="reference_truck")
    ap.add_argument("--mass", type=positive_float, default=25000.0, help="kg (default 25000)")
    ap.add_argument("--speed-kmh", type=positive_float, default=25.0)
    ap.add_argument(
        "--mode",
        choices=["Mc", "Me", "Mm"],
        default="Me",
        help="mode after the switch (its traction recovers the speed)",
    )
    ap.add_argument("--lambda-t", type=number, default=-25e3, help="J/s (default -25000)")
    ap.add_argument("--tau", type=positive_float, default=1.0, help="open driveline time (s)")
    a = ap.parse_args(argv)
    vp = load_vehicle(a.vehicle).replace(mass=a.mass)
    rows = table_a2(
        vp,
        (0.0, 6.0, 12.0),
        a.speed_kmh * KMH,
        a.tau,
        SwitchCostParams(lambda_t=a.lambda_t),
        MODE_SHORT.index(a.mode),
    )
    if a.json:
        print(
            json.dumps({"mass_kg": a.mass, "speed_kmh": a.speed_kmh, "mode": a.mode, "rows": rows})
        )
        return 0
    print(
        f"Table A2: {a.tau:g} s open driveline at {a.speed_kmh:g} km/h, {a.mass:g} kg, "
        f"recovery in {a.mode} (F_max = {rows[0]['F_max_N'] / 1e3:.1f} kN), "
        f"lambda_t = {a.lambda_t / 1e3:g} kJ/s"
    )
    print(f"{'slope':>6} {'speed loss m/s':>15} {'time loss s':>12} {'cost kJ':>8}   paper")
    for r in rows:
        p = PAPER.get(r["slope_pct"])
        ps_ = "" if p is None else f"{p[0]:.3g} / {p[1]:.2g} / {p[2]:.2g}"
        print(
            f"{r['slope_pct']:5.0f}% {r['speed_loss_mps']:15.3f} {r['time_loss_s']:12.3f} "
            f"{r['cost_kJ']:8.2f}   {ps_}"
        )
    return 0


if __name__ == "__main__":
    from jaxems.cli import script_main

    raise SystemExit(script_main("table_a2", main))
