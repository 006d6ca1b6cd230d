"""Fleet throughput of the strategies: configurations per second on one route (a benchmark).

    python benchmarks/bench_sweep.py [--route LongHaul] [--batch 1024] [--strategies ...]
                                     [--repeats 3] [--precision float32] [--json]
                                     [--devices N[,N..]] [--chunk C] [--plain | --compare-plain]
                                     [--scaling [--scaling-strategy conventional[,..]]
                                      [--scaling-batch 64] [--scaling-lengths 1,2,4]
                                      [--scaling-batches 64,128,...,4096]]
                                     [--emitters library|elemental|fusion] [--in-process]
                                     [--option NAME=VALUE ...]

Each measurement runs in its own Python subprocess (so that peak_rss_MB is that run's own
resident high-water mark and the device count can differ between runs). In it `batch` vehicle
configurations (masses 15-40 t x battery sizes 1-8 MJ, a grid cycled to the batch) run one
strategy on the route: the first call compiles (compile_s: JAX's own tracing, lowering and XLA
compilation durations during that call, from `jax.monitoring`; first_s: its wall time), then
`repeats` timed calls give median_s and
configs_per_s = batch / median_s. cpu_s_per_config is the process's user + system CPU time per
configuration over the timed calls: on a shared machine it moves less than wall time, and
cores_busy (CPU time / wall time) shows how many cores a run got. busiest_threads_cpu_s: CPU
seconds of the process's four busiest threads over the timed calls (with n devices, n threads
should share the work evenly: evidence of parallel devices even when the machine is loaded).

Paths:
- sharded (default): `jaxems.shard.map_batch` over `strategies._kernel(strategy, dt, n_steps,
  opts)` (opts: `Options()` resolved for the vehicles as `simulate_batch` does) with the route
  and `SwitchCostParams()` shared, on `--devices` host devices (default: all cores;
  `use_host_devices` runs before JAX starts), `--chunk` configurations vmapped at once per
  device (default: the strategy's own, `strategies.default_chunk`, as `simulate_batch` takes
  it). A comma list (`--devices 1,2`) measures each count in turn and reports
  speedup_vs_1_device (wall-time ratio).
- plain (`--plain`): `strategies.simulate_batch(..., chunk=None, devices=1)`, the whole batch
  in one vmap on one device (the path before sharding), in a process with one device.
  `--compare-plain` measures both and reports speedup_vs_plain and the largest relative
  difference of fuel_J between the paths.

Both paths compile the batch program as `simulate_batch` does (`strategies.BATCH_ELEMENTAL`: XLA's
elemental CPU emitters for every strategy but the conventional truck, the MPC and the
eco-driving; see `jaxems.xla`). `--emitters elemental` or `fusion` compiles every strategy's
batch with one of them, to compare.

`--option NAME=VALUE` (repeatable) sets a field of `strategies.Options` for every strategy
measured, checked as a sweep file's options table is (`sweep.option_pairs`; one that no
measured strategy depends on is refused, as it would time what it ignores); VALUE is
a TOML value (`--option sustain=false`, `--option n_iter=3`). The JSON lists them under
"options".

With --json one object on stdout:

    {"route": .., "batch": .., "precision": .., "devices": [..], "chunk": .., "machine": {..},
     "code": {"commit": .., "jaxems_dirty": .., "jaxems_sha256": ..}, "command": ..,
     "strategies": {NAME: {"configs_per_s": .., "compile_s": .., "peak_rss_MB": ..,
       "median_s": .., "s_per_config": .., "cpu_s_per_config": .., "times_s": [..], ..,
       ["by_devices": {"1": {..}, "2": {..}}, "speedup_vs_1_device": ..,]
       ["plain": {..}, "speedup_vs_plain": .., "max_rel_diff_fuel_vs_plain": ..]}},
     ["scaling": {NAME: {"length": [..], "batch": [..], "length_ratio": {..},
                         "batch_ratio": {..}}}]}

--scaling measures, for each --scaling-strategy, wall time against route length (the route
tiled 1x, 2x, 4x end to end: `tile_route`) at --scaling-batch configurations, and against the
batch size (--scaling-batches) on the route itself; it replaces the per-strategy throughput
runs. Ratios time(k x)/time(1 x) (and time(B)/time(B0)) near k (B/B0) mean linear scaling;
*_ratio also lists the ratio divided by the size ratio (1.0 = linear).

Timings are wall-clock on a shared machine: compare ratios measured in one run, quote medians.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

DEFAULT_BATCHES = "64,128,256,512,1024,2048,4096"
COMPILE_EVENTS = ("/jax/core/compile/jaxpr_trace_duration",
                  "/jax/core/compile/jaxpr_to_mlir_module_duration",
                  "/jax/core/compile/backend_compile_duration")


def vehicles(n: int, dtype):
    """n configurations: masses 15-40 t x battery sizes 1-8 MJ (a grid, cycled to n)."""
    import jax

    from jaxems.params import load_vehicle, stack_vehicles

    base = load_vehicle()
    masses = np.linspace(15e3, 40e3, 8)
    batts = np.linspace(1e6, 8e6, 8)
    pts = [(m, b) for m in masses for b in batts]
    vps = [base.replace(mass=pts[i % len(pts)][0], E_b_max=pts[i % len(pts)][1])
           for i in range(n)]
    stack = stack_vehicles(vps)
    return jax.tree_util.tree_map(lambda a: np.asarray(a, dtype), stack)


def tile_route(route, k: int):
    """The route driven k times end to end: (N,) leaves -> a route of k (n - 1) + 1 nodes.

    Node positions are i * ds, so copy j's nodes continue the grid after copy j - 1's last
    node, which is also copy j's first node: at each joint the speed limit is the smaller of
    the two, the stop times add (an end stop followed by a start stop is one stop), and the
    grade is the next copy's first cell. length = k L; padded to the route bucket.
    """
    from jaxems.route import BUCKET, Route, _round_up, n_nodes, pad_route

    if k < 1:
        raise ValueError(f"tile_route: k must be >= 1 (got {k})")
    r = Route(*(np.asarray(x) for x in route))
    n = n_nodes(r)
    g, vmax, stop = r.grade[:n], r.vmax[:n], r.stop[:n]
    G, V, S = [g[:-1]], [vmax[:-1]], [stop[:-1]]
    joint_v, joint_s = vmax[-1], stop[-1]
    for _ in range(1, k):
        V.append(np.array([min(joint_v, vmax[0])]))
        S.append(np.array([joint_s + stop[0]]))
        G.append(g[:1])
        G.append(g[1:-1])
        V.append(vmax[1:-1])
        S.append(stop[1:-1])
    G.append(g[-1:])
    V.append(vmax[-1:])
    S.append(stop[-1:])
    grade, vm, st = (np.concatenate(a) for a in (G, V, S))
    m = grade.shape[0]
    assert m == k * (n - 1) + 1
    out = Route(grade=grade, vmax=vm, stop=st, mask=np.ones(m, bool), ds=r.ds,
                length=np.float64(k * float(r.length)))
    return pad_route(out, _round_up(m, BUCKET))


# ------------------------------------------------------------------------------ one run
def thread_cpu_s() -> dict[str, float]:
    """CPU seconds (user + system) of each thread of this process (Linux /proc; else {})."""
    out = {}
    tick = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
    for stat in Path("/proc/self/task").glob("*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        out[stat.parent.name] = (int(fields[11]) + int(fields[12])) / tick
    return out


def measure(spec: dict) -> dict:
    """One measurement in this process (see the module docstring); spec keys: mode ('sharded'
    or 'plain'), strategy, route, tile, batch, devices, chunk, precision, repeats."""
    from jaxems.shard import use_host_devices

    use_host_devices(1 if spec["mode"] == "plain" else int(spec["devices"]))
    import jax
    import jax.monitoring

    x64 = spec["precision"] == "float64"
    jax.config.update("jax_enable_x64", x64)
    from jaxems import strategies as st
    from jaxems import switching as sw
    from jaxems.io import load_route
    from jaxems.params import VehicleParams
    from jaxems.shard import map_batch

    dtype = np.float64 if x64 else np.float32
    route = load_route(spec["route"])
    if spec["tile"] > 1:
        route = tile_route(route, spec["tile"])
    B, name = spec["batch"], spec["strategy"]
    vps = vehicles(B, dtype)
    n_steps = st.steps_for_batch(route, vps)
    if spec["chunk"] is None:  # the strategy's default, as simulate_batch takes it
        spec = {**spec, "chunk": st.default_chunk(name, n_steps=int(n_steps),
                                                  itemsize=np.dtype(dtype).itemsize)}

    if spec.get("emitters", "library") != "library":  # one XLA CPU code generator for all
        st.BATCH_ELEMENTAL[name] = spec["emitters"] == "elemental"
    elemental = getattr(st, "BATCH_ELEMENTAL", {}).get(name)  # None: code before xla.jit
    opts = st.Options()._replace(**spec.get("options", {}))
    if hasattr(st, "resolve_options"):  # static choices made from the vehicles, as
        opts = st.resolve_options(opts, vps)  # simulate_batch makes them
    if spec["mode"] == "plain":
        def call():  # the whole batch in one vmap on one device
            return st.simulate_batch(route, vps, name, n_steps=n_steps, chunk=None, devices=1,
                                     options=opts)
    else:
        kern = st._kernel(name, 1.0, n_steps, opts)
        params = sw.SwitchCostParams()
        vp_host = VehicleParams(*(np.asarray(x) for x in vps))

        def fn(shared, vp):
            return kern(shared[0], vp, shared[1]).metrics

        def call():
            kw = {} if elemental is None else {"elemental": elemental}
            m = map_batch(fn, vps, shared=(route, params), chunk=spec["chunk"], **kw)
            return st._fields(m, vp_host)

    compile_events = []

    def on_event(event, duration, **kw):
        if event in COMPILE_EVENTS:
            compile_events.append(duration)

    jax.monitoring.register_event_duration_secs_listener(on_event)
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    call()
    first = time.perf_counter() - t0
    compile_s = sum(compile_events)
    times = []
    r0, th0 = resource.getrusage(resource.RUSAGE_SELF), thread_cpu_s()
    for _ in range(max(1, spec["repeats"])):
        t0 = time.perf_counter()
        out = call()
        times.append(time.perf_counter() - t0)
    r1, th1 = resource.getrusage(resource.RUSAGE_SELF), thread_cpu_s()
    busiest = sorted((th1[k] - th0.get(k, 0.0) for k in th1), reverse=True)[:4]
    cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
    med = statistics.median(times)
    dev = jax.devices()[0]
    peak = st.device_memory("peak_bytes_in_use")
    return {
        "backend": dev.platform, "device_kind": dev.device_kind,
        "peak_device_MB": None if peak is None else peak / 2**20,
        "mode": spec["mode"], "strategy": name, "batch": B, "tile": spec["tile"],
        "devices": len(jax.devices()), "chunk": spec["chunk"] if spec["mode"] != "plain"
        else None, "n_steps": int(n_steps), "length_m": float(np.asarray(route.length)),
        "elemental": elemental, "configs_per_s": B / med, "median_s": med, "s_per_config": med / B,
        "compile_s": compile_s, "first_s": first, "times_s": times,
        "cpu_s_per_config": cpu / (B * len(times)), "cores_busy": cpu / sum(times),
        "busiest_threads_cpu_s": busiest,
        "peak_rss_MB": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "loadavg_1min": [load0, os.getloadavg()[0]],
        "status_ok": int(np.sum(out["status"] == "ok")),
        "fuel_J": [float(x) for x in np.asarray(out["fuel_J"])],
    }


def run_spec(spec: dict, in_process: bool) -> dict:
    """`measure` in a fresh subprocess (or here with --in-process); progress on stderr."""
    if in_process:
        res = measure(spec)
    else:
        cmd = [sys.executable, str(Path(__file__).resolve()), "--child", json.dumps(spec)]
        p = subprocess.run(cmd, stdout=subprocess.PIPE, text=True)
        if p.returncode != 0:
            raise SystemExit(f"bench_sweep: run {spec} failed (exit {p.returncode})")
        res = json.loads(p.stdout.strip().splitlines()[-1])
    dev = "plain" if res["mode"] == "plain" else f"{res['devices']} dev chunk {res['chunk']}"
    print(f"{res['strategy']:15s} x{res['tile']} B={res['batch']:5d} {dev:18s} "
          f"{res['configs_per_s']:9.2f} configs/s  median {res['median_s']:8.2f} s  "
          f"compile {res['compile_s']:6.1f} s  cpu/config {res['cpu_s_per_config']:.3f} s  "
          f"cores {res['cores_busy']:.2f}  peak RSS {res['peak_rss_MB']:7.0f} MB  "
          f"load {res['loadavg_1min'][0]:.1f}", file=sys.stderr, flush=True)
    return res


def source_hash(package: Path) -> str:
    """SHA-256 (12 hex digits) of a package's files: their paths relative to it and their
    bytes, in sorted order, caches left out. It names the code measured where git cannot (a
    copy of a working tree whose .git is not the tree's, as on a lent GPU machine)."""
    h = hashlib.sha256()
    for f in sorted(p for p in package.rglob("*") if p.is_file()
                    and "__pycache__" not in p.parts and p.suffix != ".pyc"):
        h.update(f.relative_to(package).as_posix().encode() + b"\0" + f.read_bytes() + b"\0")
    return h.hexdigest()[:12]


def code_version() -> dict:
    """The git commit of the tree measured, whether jaxems/ had uncommitted changes, and the
    hash of jaxems/'s files (`source_hash`): of the jaxems imported (another checkout on
    PYTHONPATH, to compare two versions), not of this script's tree."""
    import jaxems

    root = Path(jaxems.__file__).resolve().parents[1]

    def git(*a):
        try:
            return subprocess.run(["git", *a], cwd=root, capture_output=True, text=True,
                                  timeout=10).stdout.strip()
        except (OSError, subprocess.SubprocessError):
            return ""

    return {"commit": git("rev-parse", "--short", "HEAD"),
            "jaxems_dirty": bool(git("status", "--porcelain", "--", "jaxems")),
            "jaxems_sha256": source_hash(root / "jaxems")}


def _public(res: dict, keep_fuel: bool) -> dict:
    """A run's entry in the JSON: fuel_J (per configuration) only with --keep-fuel."""
    return {k: v for k, v in res.items() if keep_fuel or k != "fuel_J"}


def _rel_diff(a, b) -> float:
    a, b = np.asarray(a), np.asarray(b)
    return float(np.max(np.abs(a - b) / np.maximum(np.abs(b), 1e-30)))


def throughput(args, devices: list[int], base: dict) -> dict:
    out = {}
    for name in args.strategies.split(","):
        runs = {}
        if not args.plain:
            for n in devices:
                runs[n] = run_spec({**base, "mode": "sharded", "strategy": name,
                                    "devices": n}, args.in_process)
        plain = None
        if args.plain or args.compare_plain:
            plain = run_spec({**base, "mode": "plain", "strategy": name, "devices": 1},
                             args.in_process)
        if args.plain:
            out[name] = _public(plain, args.keep_fuel)
            continue
        top = runs[max(devices)]
        entry = _public(top, args.keep_fuel)
        if len(runs) > 1:
            entry["by_devices"] = {str(n): _public(r, args.keep_fuel) for n, r in runs.items()}
            if 1 in runs:
                entry["speedup_vs_1_device"] = runs[1]["median_s"] / top["median_s"]
        if plain is not None:
            entry["plain"] = _public(plain, args.keep_fuel)
            entry["speedup_vs_plain"] = plain["median_s"] / top["median_s"]
            entry["max_rel_diff_fuel_vs_plain"] = _rel_diff(top["fuel_J"], plain["fuel_J"])
        out[name] = entry
    return out


def _ratios(points: list[dict], key: str) -> dict:
    p0 = points[0]
    out = {}
    for p in points[1:]:
        size = p[key] / p0[key]
        r = p["median_s"] / p0["median_s"]
        out[f"{p[key]}/{p0[key]}"] = {"time_ratio": r, "size_ratio": size,
                                      "per_size": r / size}
    return out


def scaling(args, base: dict) -> dict:
    out = {}
    n = max(args.devices_list)
    lengths = [int(x) for x in args.scaling_lengths.split(",")]
    batches = [int(x) for x in args.scaling_batches.split(",")]
    for name in args.scaling_strategy.split(","):
        spec = {**base, "mode": "sharded", "strategy": name, "devices": n}
        by_len = [_public(run_spec({**spec, "tile": k, "batch": args.scaling_batch},
                                   args.in_process), args.keep_fuel) for k in lengths]
        by_batch = [_public(run_spec({**spec, "tile": 1, "batch": b}, args.in_process),
                            args.keep_fuel) for b in batches]
        out[name] = {"length": by_len, "batch": by_batch,
                     "length_ratio": _ratios(by_len, "tile"),
                     "batch_ratio": _ratios(by_batch, "batch")}
    return out


def parse_options(pairs: list[str], strategies: list[str]) -> dict:
    """{name: value} from NAME=VALUE strings (`jaxems.sweep.option_pairs`), each one an option
    that at least one of `strategies` depends on; SystemExit naming the bad one."""
    from jaxems.sweep import SweepError, option_pairs

    try:
        return option_pairs(pairs, strategy=strategies)
    except SweepError as e:
        raise SystemExit(f"bench_sweep: {e}") from None


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--route", default="LongHaul")
    ap.add_argument("--batch", type=int, default=1024)
    ap.add_argument("--strategies", default="conventional,baseline,multilevel,multilevel-mpc")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--precision", choices=("float32", "float64"), default="float32")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--devices", default=str(os.cpu_count() or 1),
                    help="host devices for the sharded path, or a comma list to compare")
    ap.add_argument("--chunk", type=int, default=None,
                    help="most configurations vmapped at once per device (default: each "
                         "strategy's, strategies.default_chunk: on a CPU 4 for multilevel, "
                         "1, unbatched, for multilevel-mpc, multilevel-eco and dp-bound, 16 "
                         "for conventional and baseline; on a GPU what its memory holds)")
    g = ap.add_mutually_exclusive_group()
    g.add_argument("--plain", action="store_true", help="time simulate_batch only")
    g.add_argument("--compare-plain", action="store_true",
                   help="time simulate_batch as well and report the speed-up")
    ap.add_argument("--scaling", action="store_true")
    ap.add_argument("--scaling-strategy", default="conventional")
    ap.add_argument("--scaling-batch", type=int, default=64)
    ap.add_argument("--scaling-lengths", default="1,2,4")
    ap.add_argument("--scaling-batches", default=DEFAULT_BATCHES)
    ap.add_argument("--emitters", choices=("library", "elemental", "fusion"), default="library",
                    help="XLA CPU code generator of the batch program: the library's choice "
                    "per strategy (strategies.BATCH_ELEMENTAL) or one for every strategy")
    ap.add_argument("--in-process", action="store_true",
                    help="no subprocesses (peak RSS then accumulates over runs)")
    ap.add_argument("--option", action="append", default=[], metavar="NAME=VALUE",
                    help="a strategies.Options field for every strategy (repeatable)")
    ap.add_argument("--keep-fuel", action="store_true",
                    help="keep each run's fuel_J per configuration in the JSON (to compare "
                         "backends: configuration i is grid point i mod 64)")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        print(json.dumps(measure(json.loads(args.child))))
        return 0
    try:
        args.devices_list = [int(x) for x in args.devices.split(",")]
    except ValueError:
        ap.error(f"--devices: whole numbers separated by commas (got {args.devices!r})")
    if min(args.devices_list) < 1 or (args.chunk is not None and args.chunk < 1) or args.batch < 1:
        ap.error("--devices, --chunk and --batch must be >= 1")
    if args.in_process and len(set(args.devices_list)) > 1:
        ap.error("--in-process measures one device count (the backend starts once)")
    measured = (args.scaling_strategy if args.scaling else args.strategies).split(",")
    options = parse_options(args.option, [m.strip() for m in measured])
    base = {"route": args.route, "tile": 1, "batch": args.batch, "chunk": args.chunk,
            "precision": args.precision, "repeats": args.repeats, "emitters": args.emitters,
            "options": options}
    out = {"route": args.route, "batch": args.batch, "precision": args.precision,
           "devices": args.devices_list, "chunk": args.chunk, "options": options,
           "machine": {"cpu_count": os.cpu_count(), "platform": platform.platform(),
                       "loadavg_start": list(os.getloadavg())},
           "code": code_version(),
           "command": "python benchmarks/bench_sweep.py " + " ".join(
               sys.argv[1:] if argv is None else argv),
           "strategies": {}}
    if args.scaling:
        out["scaling"] = scaling(args, base)
    else:
        out["strategies"] = throughput(args, args.devices_list, base)
    out["machine"]["loadavg_end"] = list(os.getloadavg())
    if args.json:
        print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
