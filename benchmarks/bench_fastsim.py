"""FASTSim 3 against jaxems: simulated seconds per wall second on one speed trace (a benchmark).

    python benchmarks/bench_fastsim.py [--route LongHaul] [--repeats 3] [--batch 64]
        [--batch-slow 8] [--repeats-slow 1] [--strategies conventional,baseline,multilevel]
        [--vehicle 2021_Hyundai_Sonata_Hybrid_Blue_thrml.yaml] [--procs N] [--json]

The trace is jaxems's Level 3 prediction of the route for the reference truck at 20 t (Table 8),
float32, dt = 1 s, turned into a time-based FASTSim cycle (`fastsim_cycle`): the valid steps'
times t_k, the *instantaneous* speed v_ref(t_k) (FASTSim integrates distance with the mean of
two consecutive speeds, exact within Level 3's constant-acceleration cells) and the mean
gradient of each step (FASTSim's grade[i] applies to the step from t_{i-1} to t_i, so it is
Level 3's grade[i-1]), plus a closing point at the end of the trip with the route's end speed.

FASTSim (NREL, PyPI ``fastsim``, Rust core; ``pip install -e '.[bench]'``) simulates one of its
bundled HEVs (a passenger car, not our truck: the trace is the same, the vehicle is not) with
its rule-based controller, ``SimDrive.run()`` (which repeats the trip until the battery's state
of charge balances), without saving histories (``save_interval = None``) and letting the car
fall behind the trace where it lacks power. The default car, the 2021 Hyundai Sonata Hybrid
(with FASTSim's cabin, HVAC, engine and battery thermal models), follows the whole LongHaul
trace; the 2016 Prius (no thermal models) takes about as long but falls behind on the steepest
climbs (`trace_met` False). After a warm-up run, the median of `repeats` runs
gives sim_s_per_wall_s = cycle seconds / wall seconds for one process; with --procs N > 1 also
the throughput of N worker processes running trips side by side (``sim_s_per_wall_s_procs``).

jaxems runs `simulate_batch` per strategy on a batch of configurations that all drive this trace
(20 t; battery sizes 1-8 MJ, which Level 3 does not see): after a compiling call, the median of
`repeats` calls gives configs_per_s and sim_s_per_wall_s = (sum of the runs' trip times) / wall.
The slow strategies (multilevel, multilevel-mpc, dp-bound) use --batch-slow configurations and
--repeats-slow timed calls (default 1: a call takes minutes).
cpu_per_wall is process CPU seconds per wall second during the timed calls (how many cores were
busy) and sim_s_per_cpu_s simulated seconds per CPU second of the process (all its threads):
steadier than wall time on a loaded machine; ratio_cpu compares those. With --json one object:

    {"route": .., "cycle_s": .., "fastsim": {"sim_s_per_wall_s": .., "wall_s": .., "vehicle": ..,
     ...}, "jaxems": {NAME: {"sim_s_per_wall_s": .., "configs_per_s": .., "batch": .., ...}},
     "ratio": {NAME: jaxems / fastsim}}

Timings are wall-clock on a shared machine: compare ratios measured in one run.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time

import numpy as np

DEFAULT_VEHICLE = "2021_Hyundai_Sonata_Hybrid_Blue_thrml.yaml"
SLOW = ("multilevel", "multilevel-mpc", "dp-bound")
INSTALL_HINT = "FASTSim is not installed: pip install -e '.[bench]' (PyPI package fastsim>=3.1)"


# ------------------------------------------------------------------------------------ the trace
def fastsim_cycle(pred) -> dict[str, np.ndarray]:
    """A FASTSim time-based cycle from a Level 3 `Prediction` of ONE route.

    pred: `jaxems.Prediction` with (T,) arrays (mask, v_ref, grade) and its `profile`.
    Returns float64 arrays of shape (K + 1,), K = number of valid steps: ``time_seconds``
    t_k = k dt; ``speed_meters_per_second`` the instantaneous speed v_ref(t_k), and at t_K the
    route's end speed (0 at a final stop); ``grade`` (rise/run) where grade[i] is Level 3's mean
    gradient over the step [t_{i-1}, t_i] (grade[0] repeats grade[1]). Keys are FASTSim's
    `Cycle.from_dict` field names.
    """
    mask = np.asarray(pred.mask, bool)
    if mask.ndim != 1:
        raise ValueError("fastsim_cycle: one route expected (pred.mask of shape (T,))")
    K = int(mask.sum())
    if K == 0 or not mask[:K].all():
        raise ValueError("fastsim_cycle: the prediction's valid steps must be a non-empty prefix")
    dt = float(pred.dt)
    node_mask = np.asarray(pred.profile.mask, bool)
    v_end = float(np.asarray(pred.profile.v, np.float64)[np.nonzero(node_mask)[0][-1]])
    speed = np.append(np.asarray(pred.v_ref, np.float64)[:K], v_end)
    g = np.asarray(pred.grade, np.float64)[:K]
    return {
        "time_seconds": np.arange(K + 1, dtype=np.float64) * dt,
        "speed_meters_per_second": np.maximum(speed, 0.0),
        "grade": np.concatenate([g[:1], g]),
    }


def trace_distance_m(cycle: dict) -> float:
    """Distance (m) FASTSim covers on the cycle when it meets it: trapezoid of the speeds."""
    v, t = cycle["speed_meters_per_second"], cycle["time_seconds"]
    return float(np.sum(0.5 * (v[1:] + v[:-1]) * np.diff(t)))


def trace_rise_m(cycle: dict) -> float:
    """Elevation gain (m) FASTSim sees: sum of grade[i] times the distance of step i."""
    v, t = cycle["speed_meters_per_second"], cycle["time_seconds"]
    return float(np.sum(cycle["grade"][1:] * 0.5 * (v[1:] + v[:-1]) * np.diff(t)))


def reference_truck(mass_kg: float = 20000.0):
    """The reference truck at `mass_kg` (Table 8: 20 t)."""
    from jaxems.params import load_vehicle, with_overrides

    return with_overrides(load_vehicle(), mass_kg=mass_kg)


def level3_prediction(route, vp, dt: float = 1.0):
    """Level 3 of `route` for one vehicle `vp` on a dt grid (`predict_velocity`)."""
    from jaxems.levels.velocity import predict_velocity

    return predict_velocity(route, vp, dt=dt)


# ------------------------------------------------------------------------------------- FASTSim
def _require_fastsim():
    try:
        import fastsim
    except ImportError as e:
        raise SystemExit(f"bench_fastsim: {INSTALL_HINT} ({e})") from None
    return fastsim


def make_simdrive(cycle: dict, vehicle: str = DEFAULT_VEHICLE):
    """A FASTSim `SimDrive` of a bundled vehicle on `cycle` (histories off, trace misses
    allowed: the car falls behind where it lacks power instead of raising)."""
    fsim = _require_fastsim()
    cyc = fsim.Cycle.from_dict({k: np.asarray(v, np.float64).tolist() for k, v in cycle.items()})
    veh = fsim.Vehicle.from_resource(vehicle)
    veh.set_save_interval(None)
    sp = fsim.SimParams.default().to_dict()
    sp["trace_miss_opts"] = "Allow"
    return fsim.SimDrive(veh, cyc, fsim.SimParams.from_dict(sp))


def drive(sd, balance: bool = True) -> None:
    """Run a `SimDrive` over its cycle. balance: `run()` (`walk()` before FASTSim 3.1), which for
    an HEV repeats the trip from the last final state of charge until it balances (FASTSim
    raises after 5 trips that do not); False: one trip from FASTSim's initial state of charge
    (`run_once()`)."""
    if balance:
        (sd.run if hasattr(sd, "run") else sd.walk)()
    else:
        (sd.run_once if hasattr(sd, "run_once") else sd.walk_once)()


def fastsim_summary(sd) -> dict:
    """Fuel and trace figures of a `SimDrive` that has run (for the record)."""
    d = sd.to_dict()
    st = d["veh"]["state"]
    (pt_name, pt), = d["veh"]["pt_type"].items()
    out = {
        "vehicle_name": d["veh"].get("name"),
        "powertrain": pt_name,
        "mass_kg": d["veh"].get("mass_kilograms"),
        "fuel_MJ": pt["fc"]["state"]["energy_fuel_joules"] / 1e6,
        "distance_m": st["dist_meters"],
        "trace_met": bool(st["cyc_met_overall"]),
    }
    if "res" in pt:
        out["soc_final"] = pt["res"]["state"]["soc"]
    if "soc_bal_iters" in pt:
        out["soc_balance_trips"] = pt["soc_bal_iters"]
    return out


def time_fastsim(cycle: dict, vehicle: str, repeats: int) -> dict:
    """Median wall time of `drive` (`SimDrive.run()`) over `repeats` runs after a warm-up, each
    on a fresh copy of the same unrun `SimDrive`. Where FASTSim's state-of-charge balancing does
    not converge, one trip per run (`soc_balanced` False)."""
    sd0 = make_simdrive(cycle, vehicle)
    balance = True
    try:
        drive(sd0.copy())  # warm-up
    except RuntimeError as e:
        if "SOC balancing" not in str(e):
            raise
        balance = False
        drive(sd0.copy(), balance)
    times, cpu = [], []
    for _ in range(max(1, repeats)):
        sd = sd0.copy()
        c0, t0 = time.process_time(), time.perf_counter()
        drive(sd, balance)
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    wall = statistics.median(times)
    cycle_s = float(cycle["time_seconds"][-1] - cycle["time_seconds"][0])
    return {"vehicle": vehicle, "wall_s": wall, "sim_s_per_wall_s": cycle_s / wall,
            "sim_s_per_cpu_s": cycle_s * len(cpu) / sum(cpu),
            "cpu_per_wall": sum(cpu) / sum(times), "repeats": len(times),
            "soc_balanced": balance, **fastsim_summary(sd)}


_W: dict = {}


def _worker_init(cycle: dict, vehicle: str, balance: bool):
    _W["sd"] = make_simdrive(cycle, vehicle)
    _W["balance"] = balance
    drive(_W["sd"].copy(), balance)  # warm-up in each worker


def _worker_run(_):
    drive(_W["sd"].copy(), _W["balance"])
    return 0


def time_fastsim_procs(cycle: dict, vehicle: str, procs: int, repeats: int,
                       balance: bool = True) -> dict:
    """Throughput of `procs` worker processes (spawned, warmed up) running 2 * procs trips per
    timed round; median over `repeats` rounds."""
    import multiprocessing as mp

    ctx = mp.get_context("spawn")
    n = 2 * procs
    cycle_s = float(cycle["time_seconds"][-1] - cycle["time_seconds"][0])
    with ctx.Pool(procs, initializer=_worker_init, initargs=(cycle, vehicle, balance)) as pool:
        pool.map(_worker_run, range(procs), chunksize=1)
        times = []
        for _ in range(max(1, repeats)):
            t0 = time.perf_counter()
            pool.map(_worker_run, range(n), chunksize=1)
            times.append(time.perf_counter() - t0)
    wall = statistics.median(times)
    return {"procs": procs, "trips": n, "wall_s": wall, "sim_s_per_wall_s": n * cycle_s / wall}


# -------------------------------------------------------------------------------------- jaxems
def truck_batch(n: int, mass_kg: float = 20000.0, dtype=np.float32):
    """n configurations of the reference truck at `mass_kg` with battery sizes 1-8 MJ (Level 3,
    hence the speed trace, does not depend on the battery)."""
    import jax

    from jaxems.params import stack_vehicles

    base = reference_truck(mass_kg)
    batts = np.linspace(1e6, 8e6, n) if n > 1 else np.array([float(base.E_b_max)])
    stack = stack_vehicles([base.replace(E_b_max=float(b)) for b in batts])
    return jax.tree_util.tree_map(lambda a: np.asarray(a, dtype), stack)


def time_jaxems(route, strategy: str, batch: int, repeats: int, mass_kg: float = 20000.0):
    """Median wall time of `simulate_batch` for one strategy on `batch` configurations (float32,
    after a compiling call)."""
    from jaxems.strategies import simulate_batch, steps_for_batch

    vps = truck_batch(batch, mass_kg)
    n_steps = steps_for_batch(route, vps)
    t0 = time.perf_counter()
    simulate_batch(route, vps, strategy, n_steps=n_steps)
    first = time.perf_counter() - t0
    times, cpu = [], []
    for _ in range(max(1, repeats)):
        c0, t0 = time.process_time(), time.perf_counter()
        out = simulate_batch(route, vps, strategy, n_steps=n_steps)
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    wall = statistics.median(times)
    sim_s = float(np.sum(out["trip_time_s"]))
    return {"batch": batch, "configs_per_s": batch / wall, "sim_s_per_wall_s": sim_s / wall,
            "sim_s_per_cpu_s": sim_s * len(cpu) / sum(cpu), "repeats": len(times),
            "median_s": wall, "compile_s": max(first - wall, 0.0),
            "cpu_per_wall": sum(cpu) / sum(times), "n_steps": n_steps,
            "trip_time_s": sim_s / batch,
            "not_ok": int(np.sum(np.asarray(out["status"]) != "ok"))}


# ---------------------------------------------------------------------------------------- main
def _cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--route", default="LongHaul")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--batch-slow", type=int, default=8,
                    help=f"batch of the slow strategies ({', '.join(SLOW)})")
    ap.add_argument("--repeats-slow", type=int, default=1,
                    help="timed calls of the slow strategies (each takes minutes)")
    ap.add_argument("--strategies", default="conventional,baseline,multilevel")
    ap.add_argument("--vehicle", default=DEFAULT_VEHICLE,
                    help="a FASTSim bundled vehicle (fastsim.Vehicle.list_resources())")
    ap.add_argument("--procs", type=int, default=_cores(),
                    help="FASTSim worker processes for the parallel figure (1: none)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    if min(args.batch, args.batch_slow, args.repeats, args.repeats_slow, args.procs) < 1:
        ap.error("--batch, --batch-slow, --repeats, --repeats-slow and --procs must be at "
                 "least 1")

    fsim = _require_fastsim()  # fail before any JAX work
    names = [str(p) for p in fsim.Vehicle.list_resources()]
    if args.vehicle not in names:
        ap.error(f"--vehicle: {args.vehicle!r} is not a FASTSim vehicle ({', '.join(names)})")

    import jax

    jax.config.update("jax_enable_x64", False)
    from jaxems.io import load_route
    from jaxems.strategies import check_strategy

    strategies = [check_strategy(s) for s in args.strategies.split(",") if s]
    route = load_route(args.route)
    vp = jax.tree_util.tree_map(lambda a: np.asarray(a, np.float32), reference_truck())
    pred = level3_prediction(route, vp)
    cycle = fastsim_cycle(pred)
    cycle_s = float(cycle["time_seconds"][-1])
    log = sys.stderr
    print(f"{args.route}: Level 3 trace of the 20 t truck, {cycle_s:.0f} s, "
          f"{trace_distance_m(cycle) / 1e3:.2f} km (route {float(pred.length) / 1e3:.2f} km), "
          f"rise {trace_rise_m(cycle):.1f} m", file=log, flush=True)

    fs = time_fastsim(cycle, args.vehicle, args.repeats)
    print(f"{'FASTSim ' + fs['vehicle_name']:34s} {fs['sim_s_per_wall_s']:12.0f} sim s/s  "
          f"({fs['sim_s_per_cpu_s']:.0f} per CPU s)  "
          f"run {fs['wall_s'] * 1e3:8.1f} ms  fuel {fs['fuel_MJ']:.1f} MJ  "
          f"trace met {fs['trace_met']}", file=log, flush=True)
    if args.procs > 1:
        fs_p = time_fastsim_procs(cycle, args.vehicle, args.procs, args.repeats,
                                  fs["soc_balanced"])
        fs["sim_s_per_wall_s_procs"] = fs_p["sim_s_per_wall_s"]
        fs["procs"] = fs_p["procs"]
        print(f"{f'FASTSim x {args.procs} processes':34s} {fs_p['sim_s_per_wall_s']:12.0f} "
              f"sim s/s", file=log, flush=True)

    out = {"route": args.route, "cycle_s": cycle_s, "cycle": {
        "speed": "v_ref (instantaneous speed at each 1 s step)", "dt_s": float(pred.dt),
        "distance_m": trace_distance_m(cycle), "route_length_m": float(pred.length),
        "rise_m": trace_rise_m(cycle), "truck_mass_kg": 20000.0, "precision": "float32"},
        "fastsim": fs, "jaxems": {}, "ratio": {}, "ratio_cpu": {}, "cores": _cores()}
    if "sim_s_per_wall_s_procs" in fs:
        out["ratio_procs"] = {}
    for name in strategies:
        slow = name in SLOW
        b = args.batch_slow if slow else args.batch
        r = time_jaxems(route, name, b, args.repeats_slow if slow else args.repeats)
        out["jaxems"][name] = r
        out["ratio"][name] = r["sim_s_per_wall_s"] / fs["sim_s_per_wall_s"]
        out["ratio_cpu"][name] = r["sim_s_per_cpu_s"] / fs["sim_s_per_cpu_s"]
        if "ratio_procs" in out:
            out["ratio_procs"][name] = r["sim_s_per_wall_s"] / fs["sim_s_per_wall_s_procs"]
        print(f"{'jaxems ' + name + f' (batch {b})':34s} {r['sim_s_per_wall_s']:12.0f} sim s/s  "
              f"{r['configs_per_s']:8.2f} configs/s  x{out['ratio'][name]:.3g} FASTSim "
              f"(x{out['ratio_cpu'][name]:.3g} per CPU s)  "
              f"(compile {r['compile_s']:.0f} s, {r['cpu_per_wall']:.1f} cores busy)",
              file=log, flush=True)
    if args.json:
        print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
