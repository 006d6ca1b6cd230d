"""How the plant follows a plan: where a plan asks for battery power of an empty battery, and
the plant's fuel against the plan's, stretch by stretch.

multilevel's last plan and dp-bound's reported one (`Result.extra`) hold each step's state,
battery power and the battery energy the plan expects within the battery's limits (`E_ref`,
as the plant holds them). Where E_ref is at empty and the plan's own model
(`plan.steps_energy`) still draws from the battery, the plant cannot do what the plan
does and runs the engine instead. For each stretch of `--segment-km` the script prints the
plant's fuel (its trace's, `Trace.P_f`: the synchronisation energy the engine supplies where
the battery cannot is in the run's fuel_J only) against the plan's Level 1 split
(`powersplit.split_state` of the plan's state at its costate and the predicted demand,
before the plan's battery-power trim), the plan's
steps at an empty battery that still draw from it, and the plan's and the plant's battery
energy at the stretch's end. Float64; one vehicle, half charge.

    .venv/bin/python experiments/plan_tracking.py [--route LongHaul] [--mass 20000]
        [--battery-MJ 4] [--strategy multilevel|dp-bound] [--segment-km 6] [--json]

`--json` prints one JSON object ``{"summary": {...}, "segments": [...], "runs": [...]}`` on
stdout (runs: stretches of consecutive steps at empty that draw from the battery); progress
goes to stderr.
"""

from __future__ import annotations

import argparse
import json
import sys

import jax
from jax import config

config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from jaxems import plan as pn  # noqa: E402
from jaxems import strategies as S  # noqa: E402
from jaxems.cli import positive_float  # noqa: E402
from jaxems.levels import powersplit as ps  # noqa: E402
from jaxems.params import check_vehicle, load_vehicle, with_overrides  # noqa: E402

PLANNED = ("multilevel", "dp-bound")
EMPTY_J = 1.0  # a plan's battery "at empty": E_ref within this of 0 (J)
# the split of each step's (mode, gear) at its costate: (vp, P_d, v, lam, mode, gear), (T,) each
split_steps = jax.jit(jax.vmap(ps.split_state, in_axes=(None, 0, 0, 0, 0, 0)))


def last_plan(res) -> pn.Plan:
    """The plan the plant ran: multilevel's last iteration's, dp-bound's reported attempt's."""
    plan = res.extra.plan
    if res.strategy == "multilevel":
        plan = jax.tree_util.tree_map(lambda x: x[-1], plan)
    return jax.tree_util.tree_map(np.asarray, plan)


def tracking(res, vp, segment_m: float, dt: float = 1.0) -> dict:
    """The summary, the stretches and the runs at empty of a `Result` of a planned strategy."""
    pred, tr = res.prediction, res.trace
    plan = last_plan(res)
    mask = np.asarray(pred.mask)
    dE = np.asarray(pn.steps_energy(vp, pred, jnp.asarray(plan.mode), jnp.asarray(plan.gear),
                                    jnp.asarray(plan.P_b), dt))
    empty = mask & (plan.E_ref <= EMPTY_J) & (dE < -EMPTY_J)
    split = split_steps(vp, pred.P_d, pred.v, jnp.asarray(plan.lam), jnp.asarray(plan.mode),
                        jnp.asarray(plan.gear))
    # fuel of the steps that start before a position (the last stretch takes every step left)
    f_plan = np.concatenate([[0.0], np.cumsum(np.where(mask, np.asarray(split.P_f) * dt, 0.0))])
    f_plant = np.concatenate([[0.0], np.cumsum(np.asarray(tr.P_f) * dt)])
    s_pred, s_plant = np.asarray(pred.s), np.asarray(tr.s)
    length = float(pred.length)
    ends = np.arange(segment_m, length, segment_m)
    segments, prev = [], (0, 0)
    for n, end in enumerate(np.append(ends, length)):
        last = n == ends.size
        j = s_pred.size if last else int(np.searchsorted(s_pred, end))
        i = s_plant.size if last else int(np.searchsorted(s_plant, end))
        segments.append({
            "to_km": float(end) / 1e3,
            "plan_fuel_MJ": (f_plan[j] - f_plan[prev[0]]) / 1e6,
            "plant_fuel_MJ": (f_plant[i] - f_plant[prev[1]]) / 1e6,
            "empty_steps": int(np.sum(empty[prev[0]:j])),
            "plan_E_MJ": float(plan.E_ref[min(j, s_pred.size - 1)]) / 1e6,
            "plant_E_MJ": float(tr.E_b[min(i, s_plant.size - 1)]) / 1e6,
        })
        prev = (j, i)
    idx = np.flatnonzero(empty)
    groups = np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1) if idx.size else []
    runs = [{"from_km": float(s_pred[g[0]]) / 1e3, "to_km": float(s_pred[g[-1]]) / 1e3,
             "steps": int(g.size), "modes": sorted({int(m) for m in plan.mode[g]}),
             "asked_MJ": float(np.sum(-dE[g])) / 1e6} for g in groups]
    summary = {"route": res.route, "strategy": res.strategy,
               "mass_kg": float(np.asarray(vp.mass)),
               "battery_MJ": float(np.asarray(vp.E_b_max)) / 1e6,
               "fuel_J": float(res["fuel_J"]), "fuel_corrected_J": float(res["fuel_corrected_J"]),
               "trace_fuel_J": float(f_plant[-1]), "plan_split_fuel_J": float(f_plan[-1]),
               "empty_steps": int(empty.sum()),
               "asked_at_empty_J": float(np.sum(-dE[empty]))}
    return {"summary": summary, "segments": segments, "runs": runs}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--route", default="LongHaul")
    ap.add_argument("--mass", type=positive_float, default=20000.0)
    ap.add_argument("--battery-MJ", type=positive_float, default=None)
    ap.add_argument("--strategy", choices=PLANNED, default="multilevel")
    ap.add_argument("--segment-km", type=positive_float, default=6.0)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    vp = check_vehicle(with_overrides(load_vehicle("reference_truck"), mass_kg=args.mass,
                                      battery_MJ=args.battery_MJ))
    print(f"plan_tracking: {args.strategy} on {args.route}", file=sys.stderr, flush=True)
    res = S.simulate(args.route, vp, args.strategy)
    out = tracking(res, vp, 1e3 * args.segment_km)
    if args.json:
        print(json.dumps(out))
        return 0
    sm = out["summary"]
    print(f"{sm['strategy']} on {sm['route']}, {sm['mass_kg']:.0f} kg, {sm['battery_MJ']:g} MJ: "
          f"fuel {sm['fuel_J'] / 1e6:.3f} MJ (corrected {sm['fuel_corrected_J'] / 1e6:.3f}), "
          f"the plan's Level 1 split {sm['plan_split_fuel_J'] / 1e6:.3f} MJ; "
          f"{sm['empty_steps']} steps ask {sm['asked_at_empty_J'] / 1e6:.3f} MJ of an empty "
          f"battery")
    print(f"{'to km':>8} {'plan MJ':>9} {'plant MJ':>9} {'diff':>7} {'empty':>6} "
          f"{'E plan':>7} {'E plant':>8}")
    for g in out["segments"]:
        print(f"{g['to_km']:8.1f} {g['plan_fuel_MJ']:9.2f} {g['plant_fuel_MJ']:9.2f} "
              f"{g['plant_fuel_MJ'] - g['plan_fuel_MJ']:+7.2f} {g['empty_steps']:6d} "
              f"{g['plan_E_MJ']:7.3f} {g['plant_E_MJ']:8.3f}")
    for r in out["runs"]:
        print(f"at empty {r['from_km']:.2f}-{r['to_km']:.2f} km: {r['steps']} steps in modes "
              f"{r['modes']}, {r['asked_MJ']:.3f} MJ asked")
    return 0


if __name__ == "__main__":
    from jaxems.cli import script_main

    sys.exit(script_main("plan_tracking", main))
