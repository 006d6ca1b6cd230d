"""One run per strategy: first call (compilation included) and further calls, with each of
XLA's CPU code generators (a benchmark).

    python benchmarks/bench_compile.py [--route short_track] [--mass 25000]
                                       [--strategies conventional,...] [--emitters elemental,fusion]
                                       [--repeats 3] [--json]

For each strategy and each code generator a fresh Python process (float64, no persistent
compilation cache) calls `jaxems.simulate(route, strategy=S, mass_kg=mass)`: first_s is that
call's wall time, compilation included; then `repeats` calls with other masses (1, 2, 3 ... t
more: new array values, no recompilation) give next_s, their median. `elemental` compiles
every program of the run with XLA's elemental CPU emitters, `fusion` with XLA's default fusion
emitters (`jaxems.xla`; the library itself picks per strategy, `strategies.SINGLE_ELEMENTAL`).
fuel_J and delta_Eb_J of the first call show what the code generator changes in the results.
The processes run one after another, the two code generators of a strategy next to each other:
compare figures of one run (the machine is shared).

With --json one object on stdout: {"route": .., "mass_kg": .., "runs": [{"strategy": ..,
"emitters": .., "first_s": .., "next_s": .., "fuel_J": .., "delta_Eb_J": ..}, ...]}.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

STRATEGIES = "conventional,baseline,multilevel,multilevel-mpc,dp-bound,multilevel-eco"


def measure(spec: dict) -> dict:
    import jax

    jax.config.update("jax_enable_x64", True)
    from jaxems import strategies as S
    from jaxems import xla

    elemental = spec["emitters"] == "elemental"
    S.SINGLE_ELEMENTAL[spec["strategy"]] = elemental  # simulate's choice for this strategy
    m0, name = spec["mass"], spec["strategy"]
    t0 = time.perf_counter()
    r = S.simulate(spec["route"], strategy=name, mass_kg=m0)
    first = time.perf_counter() - t0
    times = []
    for k in range(1, spec["repeats"] + 1):
        t0 = time.perf_counter()
        S.simulate(spec["route"], strategy=name, mass_kg=m0 + 1000.0 * k)
        times.append(time.perf_counter() - t0)
    return {"strategy": name, "emitters": spec["emitters"],
            "compiler_options": xla.compiler_options() if elemental else None,
            "first_s": first, "next_s": statistics.median(times), "times_s": times,
            "fuel_J": r["fuel_J"], "delta_Eb_J": r["delta_Eb_J"],
            "loadavg_1min": os.getloadavg()[0]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--route", default="short_track")
    ap.add_argument("--mass", type=float, default=25000.0)
    ap.add_argument("--strategies", default=STRATEGIES)
    ap.add_argument("--emitters", default="elemental,fusion")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        print(json.dumps(measure(json.loads(args.child))))
        return 0
    emitters = args.emitters.split(",")
    if not set(emitters) <= {"elemental", "fusion"} or args.repeats < 1:
        ap.error("--emitters: elemental and/or fusion; --repeats >= 1")
    runs = []
    for name in args.strategies.split(","):
        for e in emitters:
            spec = {"route": args.route, "mass": args.mass, "strategy": name, "emitters": e,
                    "repeats": args.repeats}
            cmd = [sys.executable, str(Path(__file__).resolve()), "--child", json.dumps(spec)]
            p = subprocess.run(cmd, stdout=subprocess.PIPE, text=True)
            if p.returncode != 0:
                raise SystemExit(f"bench_compile: run {spec} failed (exit {p.returncode})")
            res = json.loads(p.stdout.strip().splitlines()[-1])
            runs.append(res)
            print(f"{name:15s} {e:9s} first {res['first_s']:6.1f} s  next {res['next_s']:7.3f} s"
                  f"  fuel {res['fuel_J']!r} J  dE_b {res['delta_Eb_J']!r} J  "
                  f"load {res['loadavg_1min']:.1f}", file=sys.stderr, flush=True)
    if args.json:
        print(json.dumps({"route": args.route, "mass_kg": args.mass, "runs": runs,
                          "command": "python benchmarks/bench_compile.py " + " ".join(
                              sys.argv[1:] if argv is None else argv)}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
