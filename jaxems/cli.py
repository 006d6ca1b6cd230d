"""The `jaxems` command line (also `python -m jaxems`).

    jaxems route ROUTE [--json]                          facts of a route file
    jaxems predict ROUTE [--vehicle NAME|PATH] [--mass KG] [--json] [--csv FILE]
                                                         Level 3 speed and power prediction
    jaxems simulate ROUTE [--vehicle NAME|PATH] [--mass KG] [--battery-MJ X] [--initial-soc F]
                    [--strategy NAME] [--dt S] [--n-iter N] [--option NAME=VALUE ...]
                    [--json] [--csv FILE] [--plot FILE]  one strategy on the closed-loop plant
    jaxems compare ROUTE [--vehicle ...] [--mass KG] [--battery-MJ X] [--strategies A,B,...]
                   [--option NAME=VALUE ...] [--json] [--traces DIR]
                                                         fuel and savings of several strategies

ROUTE is a `.vdri` or `.csv` file or the name of a bundled route (``short_track``,
``LongHaul``, ...). A bad file or value prints one line on stderr and exits with status 1.
Compiled programs are kept in JAX's persistent compilation cache (`cache_dir`).

Each subcommand is a `register_*` function that adds its parser and sets ``func``; new
subcommands (sweep, report) add one more `register_*` to `SUBCOMMANDS`.
"""

from __future__ import annotations

import argparse
import json
import math
import numbers
import os
import re
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

EXIT_ERROR = 1
EXIT_INTERRUPTED = 130  # 128 + SIGINT, as shells report it


class CLIError(Exception):
    """A user-facing error: printed as one line, exit status 1."""


CACHE_DIR_ENV = "JAXEMS_CACHE_DIR"


def cache_dir() -> Path | None:
    """Where the commands keep JAX's persistent compilation cache: $JAXEMS_CACHE_DIR (set and
    empty: none), else $XDG_CACHE_HOME/jaxems/jax, else ~/.cache/jaxems/jax (none without a
    home directory)."""
    if CACHE_DIR_ENV in os.environ:
        return Path(os.environ[CACHE_DIR_ENV]).expanduser() if os.environ[CACHE_DIR_ENV] else None
    try:
        base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    except RuntimeError:  # no home directory to be found
        return None
    return Path(base) / "jaxems" / "jax"


def use_compilation_cache() -> None:
    """JAX's persistent compilation cache in `cache_dir()` unless JAX has one already
    (JAX_COMPILATION_CACHE_DIR): a command's second run loads its programs instead of compiling
    them (seconds instead of a minute); a directory that cannot be made is skipped."""
    import jax

    where = cache_dir()
    if jax.config.jax_compilation_cache_dir or where is None:
        return
    try:
        where.mkdir(parents=True, exist_ok=True)
    except OSError:
        return
    jax.config.update("jax_compilation_cache_dir", str(where))


def _setup_jax() -> None:
    """float64 and the compilation cache (`use_compilation_cache`)."""
    import jax

    jax.config.update("jax_enable_x64", True)
    use_compilation_cache()


def _load_vehicle(args):
    from .params import load_vehicle, with_overrides

    vp = load_vehicle(args.vehicle)
    return with_overrides(vp, mass_kg=args.mass, battery_MJ=getattr(args, "battery_MJ", None),
                          initial_soc=getattr(args, "initial_soc", None))


def _load(args):
    from .io import load_route, resolve_route, route_name

    path = resolve_route(args.route)
    return route_name(path), path, load_route(path, ds=args.ds)


def check_output(path: str | None, flag: str, directory: bool = False) -> Path | None:
    """An output named on the command line, checked before anything runs, so that a long run
    does not end without it (else CLIError naming the flag): a file's directory exists and is
    writable and the file is no directory; with ``directory``, the path is a writable
    directory, or none yet in a writable one (the caller makes it when it writes)."""
    if path is None:
        return None
    if not path.strip():  # Path("") is the current directory
        raise CLIError(f"{flag}: expected a {'directory' if directory else 'file'} name "
                       f"(got {path!r})")
    p = Path(path)
    if p.exists() and p.is_dir() != directory:
        raise CLIError(f"{flag}: {path} is {'not ' if directory else ''}a directory")
    parent = p if p.is_dir() else p.parent
    if not parent.is_dir():
        up = nearest_existing(parent)  # afile/x.csv: afile is a file, not a missing directory
        if up.exists() and not up.is_dir():
            raise CLIError(f"{flag}: {up} is not a directory")
        raise CLIError(f"{flag}: the directory {parent} does not exist")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise CLIError(f"{flag}: the directory {parent} is not writable")
    return p


def check_not_inputs(outputs: list[tuple[str, Path | None]], route=None, vehicle=None) -> None:
    """Outputs ((flag, path) pairs) that are none of the files a command reads (its route file,
    its vehicle file), checked before anything runs: `predict r.csv --csv r.csv` wrote its
    time series over the route it had read. Else CLIError naming the flag and both files."""
    from .io import resolve_route
    from .params import vehicle_file

    inputs = [(what, p) for what, p in (
        ("the route file", None if route is None else resolve_route(route)),
        ("the vehicle file", None if vehicle is None else vehicle_file(vehicle)))
        if p is not None]
    for flag, out in outputs:
        for what, src in inputs:
            if out is not None and same_file(out, src):
                raise CLIError(f"{flag}: {out} is {what} being read ({src}); an output may not "
                               f"overwrite an input: name another file")


def same_file(a: Path, b: Path) -> bool:
    """Whether `a` and `b` are one existing file (links and other spellings of the path
    included); False where either does not exist."""
    try:
        return os.path.samefile(a, b)
    except (OSError, ValueError):
        return False


def nearest_existing(path: Path) -> Path:
    """`path` or its nearest ancestor that exists (what stands where a file or directory is to
    be made: a directory, or a file in the way); the root where none does."""
    p = Path(path)
    while not p.exists() and p.parent != p:
        p = p.parent
    return p


def write_run_files(res, vp, csv: Path | None, plot: Path | None) -> None:
    """A simulated run's time series (`Result.trace_columns`, CSV) and traces (PNG,
    `report.plot_run`), where a path is given."""
    if csv is not None:
        write_csv(csv, res.trace_columns())
    if plot is not None:
        from .report import plot_run

        plot_run(res, vp, res.strategy, plot)


def write_csv(path: Path, columns: dict) -> None:
    """Columns (name -> (n,) array) as a CSV file with a header line, written whole or not at
    all; numbers to 10 significant digits, whole numbers and text as they are."""
    import numpy as np

    from .sweep import atomic_write_bytes

    def fmt(a):
        a = np.asarray(a)
        if a.dtype.kind in "iub":
            return [str(int(x)) for x in a]
        if a.dtype.kind in "fc":
            return [f"{x:.10g}" for x in a]
        return [str(x) for x in a]

    cols = [fmt(a) for a in columns.values()]
    lines = [",".join(columns)] + [",".join(row) for row in zip(*cols, strict=True)]
    atomic_write_bytes(path, ("\n".join(lines) + "\n").encode("utf-8"))


def comma_list(text: str, what: str | None = None) -> list[str]:
    """The items of a comma-separated option, stripped, empty ones dropped; where `what` names
    the option, none at all is a ValueError naming it."""
    items = [x.strip() for x in text.split(",") if x.strip()]
    if what is not None and not items:
        raise ValueError(f"{what}: none given")
    return items


def format_or_dash(x, fmt: str) -> str:
    """x formatted with fmt (e.g. '8.3f'); a right-aligned '-' of the same width for None or
    a number that is not finite (an unfinished run's trip time: it printed nan)."""
    width = int(re.match(r"[+-]?(\d*)", fmt).group(1) or 0)
    missing = x is None or (isinstance(x, numbers.Real) and not math.isfinite(x))
    return "-".rjust(width) if missing else format(x, fmt)


# why a run has no trip time to show (a flag of its status -> the words), the first that
# applies: on a route Level 3 predicts the truck cannot climb, the plant's trip (0.0 s, or a
# hybrid's crawl up with its motor's help) is none to set against Level 3's (it printed 0.0 s,
# -100 %); an unfinished run's is NaN
NO_TRIP_TIME = {
    "infeasible-route": "an infeasible route: the truck cannot climb it, as Level 3 predicts "
                        "it; no trip time to compare",
    "unfinished": "the run did not reach the route's end: its fuel and battery figures are over "
                  "the steps it ran",
}


def no_trip_time(status: str) -> str | None:
    """Why a run of `status` ('ok' or flags joined by '+') shows no trip time ('-' in the
    `simulate` and `compare` tables), or None where it shows one."""
    flags = status.split("+")
    return next((why for flag, why in NO_TRIP_TIME.items() if flag in flags), None)


def _print_table(pairs: list[tuple[str, str]]) -> None:
    w = max(len(k) for k, _ in pairs)
    for k, v in pairs:
        print(f"{k:<{w}}  {v}")


# ------------------------------------------------------------------------------------ route
def cmd_route(args) -> int:
    """`jaxems route`: length, duration at the predicted speed, gradient range, stops."""
    from .levels.velocity import predict_velocity
    from .route import route_summary

    _setup_jax()
    name, path, route = _load(args)
    vp = _load_vehicle(args)
    pred = predict_velocity(route, vp)
    info = route_summary(route)
    trip = float(pred.trip_time)
    out = {
        "route": name,
        "file": str(path),
        "length_m": info["length_m"],
        "duration_s": trip,
        "mean_speed_km_h": info["length_m"] / trip * 3.6,
        "gradient_min_pct": info["gradient_min_pct"],
        "gradient_max_pct": info["gradient_max_pct"],
        "speed_limit_min_km_h": info["speed_limit_min_km_h"],
        "speed_limit_max_km_h": info["speed_limit_max_km_h"],
        "stops": info["stops"],
        "stop_time_s": info["stop_time_s"],
        "starts_stopped": info["starts_stopped"],
        "ends_stopped": info["ends_stopped"],
        "nodes": info["nodes"],
        "ds_m": info["ds_m"],
    }
    if args.json:
        print(json.dumps(out))
        return 0
    _print_table(
        [
            ("route", f"{name} ({path})"),
            ("length", f"{out['length_m'] / 1000:.3f} km"),
            (
                "duration",
                f"{trip:.1f} s at the predicted speed ({out['mean_speed_km_h']:.1f} km/h)",
            ),
            ("gradient", f"{out['gradient_min_pct']:+.2f} % .. {out['gradient_max_pct']:+.2f} %"),
            (
                "speed limit",
                f"{out['speed_limit_min_km_h']:.1f} .. {out['speed_limit_max_km_h']:.1f} km/h",
            ),
            ("stops", f"{out['stops']} ({out['stop_time_s']:.0f} s standing)"),
            (
                "start / end",
                f"{'standstill' if out['starts_stopped'] else 'flying'} / "
                f"{'standstill' if out['ends_stopped'] else 'free'}",
            ),
            ("grid", f"{out['nodes']} nodes, ds = {out['ds_m']:.3f} m"),
        ]
    )
    return 0


def register_route(sub) -> None:
    p = sub.add_parser(
        "route",
        help="facts of a route: length, duration, gradients, stops",
        description=cmd_route.__doc__,
    )
    p.add_argument("route", metavar="ROUTE", help=".vdri or .csv file, or a bundled route name")
    _common_vehicle(p)
    p.add_argument("--ds", type=number, default=10.0, help="distance grid step in m (default 10)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=cmd_route)


# ---------------------------------------------------------------------------------- predict
def cmd_predict(args) -> int:
    """`jaxems predict`: Level 3 speed and driveline power prediction over a route."""
    import numpy as np

    from .levels.velocity import energy_summary, predict_velocity
    from .strategies import check_dt

    dt = check_dt(args.dt)
    csv = check_output(args.csv, "--csv")
    check_not_inputs([("--csv", csv)], args.route, args.vehicle)
    _setup_jax()
    name, path, route = _load(args)
    vp = _load_vehicle(args)
    pred = predict_velocity(route, vp, dt=dt)
    out = {
        "route": name,
        "file": str(path),
        "vehicle": str(args.vehicle),
        "mass_kg": float(vp.mass),
        "dt_s": dt,
    } | energy_summary(pred)
    if csv is not None:
        m = np.asarray(pred.mask)
        names = ("t_s", "s_m", "v_m_s", "a_m_s2", "grade", "P_d_W")
        write_csv(csv, {k: np.asarray(x)[m] for k, x in zip(
            names, (pred.t, pred.s, pred.v, pred.a, pred.grade, pred.P_d), strict=True)})
    if args.json:
        print(json.dumps(out))
        return 0
    _print_table(
        [
            ("route", f"{name} ({path})"),
            ("vehicle", f"{args.vehicle}, {out['mass_kg']:.0f} kg"),
            ("trip time", f"{out['trip_time_s']:.1f} s ({out['steps']} steps of {dt:g} s)"),
            (
                "mean speed",
                f"{out['mean_speed_km_h']:.2f} km/h over {out['length_m'] / 1000:.3f} km",
            ),
            ("traction energy", f"{out['energy_traction_MJ']:.2f} MJ"),
            ("braking energy", f"{out['energy_braking_MJ']:.2f} MJ"),
            ("P_d range", f"{out['P_d_min_kW']:.1f} .. {out['P_d_max_kW']:.1f} kW"),
            ("feasible", "yes" if out["feasible"] else "NO: the truck cannot climb (crawl floor)"),
        ]
        + ([("time series", args.csv)] if args.csv else [])
    )
    return 0


def register_predict(sub) -> None:
    p = sub.add_parser(
        "predict",
        help="Level 3 velocity and power-demand prediction",
        description=cmd_predict.__doc__,
    )
    p.add_argument("route", metavar="ROUTE", help=".vdri or .csv file, or a bundled route name")
    _common_vehicle(p)
    p.add_argument("--dt", type=number, default=1.0, help="time step in s, 0.05 to 10 (default 1)")
    p.add_argument("--ds", type=number, default=10.0, help="distance grid step in m (default 10)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--csv", metavar="FILE", help="write the time series (t, s, v, a, grade, P_d)")
    p.set_defaults(func=cmd_predict)

# --------------------------------------------------------------------------------- simulate
# (JSON key, label, unit, scale, format) of the human-readable `simulate` table
SIMULATE_ROWS = [
    ("length_m", "length", "km", 1e-3, ".3f"),
    ("trip_time_s", "trip time", "s", 1.0, ".1f"),
    ("fuel_J", "fuel", "MJ", 1e-6, ".3f"),
    ("fuel_l_per_100km", "fuel", "l/100 km", 1.0, ".2f"),
    ("fuel_corrected_J", "fuel + lambda_b dE_b", "MJ", 1e-6, ".3f"),
    ("delta_Eb_J", "delta E_b (end - start)", "MJ", 1e-6, "+.3f"),
    ("Eb_min_J", "E_b min", "MJ", 1e-6, ".3f"),
    ("Eb_max_J", "E_b max", "MJ", 1e-6, ".3f"),
    ("lambda_b", "lambda_b (first)", "", 1.0, ".4f"),
    ("mode_switches", "mode switches", "", 1, "d"),
    ("gear_switches", "gear switches", "", 1, "d"),
    ("max_speed_shortfall_mps", "max speed shortfall", "m/s", 1.0, ".3f"),
    ("status", "status", "", None, ""),
    ("wall_s", "wall time", "s", 1.0, ".2f"),
]


def _json_safe(d: dict) -> dict:
    """Non-finite floats as null, so that the output is strict JSON."""
    import math

    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
            for k, v in d.items()}


def cmd_simulate(args) -> int:
    """`jaxems simulate`: one energy-management strategy on a route, closed loop on the plant.

    Prints fuel (J and l/100 km), the battery energy balance and range, the first Level 2
    costate, switch counts and the largest shortfall from the reference speed.
    """
    from .io import resolve_route, route_name
    from .report import CHARGE_SHARE, off_charge, trip_vs_level3_pct
    from .strategies import check_strategy, level2_names, simulate

    check_strategy(args.strategy)  # before anything is loaded or compiled
    if args.n_iter is not None and args.n_iter < 1:
        raise CLIError(f"--n-iter: must be a whole number >= 1 (got {args.n_iter})")
    csv, plot = check_output(args.csv, "--csv"), check_output(args.plot, "--plot")
    if plot is not None and plot.suffix.lower() != ".png":
        raise CLIError(f"--plot: the plot is a PNG: its file name ends in .png (got {args.plot})")
    if csv is not None and plot is not None and csv.resolve() == plot.resolve():
        raise CLIError(f"--csv and --plot: the same file {args.csv} (each needs its own)")
    check_not_inputs([("--csv", csv), ("--plot", plot)], args.route, args.vehicle)
    _setup_jax()
    vp = _load_vehicle(args)  # mass and battery validated here
    path = resolve_route(args.route)
    options = {}
    if args.option:  # checked before anything compiles
        from .sweep import option_pairs

        options = option_pairs(args.option, strategy=args.strategy)
    if args.n_iter is not None:
        if "n_iter" in options:
            raise CLIError("--n-iter: given twice (also as --option n_iter=...)")
        options["n_iter"] = args.n_iter
    res = simulate(str(path), vp, args.strategy, dt=args.dt, name=route_name(path), **options)
    out = res.as_dict()
    out |= {"vehicle": str(args.vehicle), "mass_kg": float(vp.mass),
            "battery_MJ": float(vp.E_b_max) / 1e6, "initial_soc": float(vp.soc0),
            "dt_s": float(args.dt), "options": options}
    # the charge-sustaining check, as sweep reports apply it (`report.off_charge`)
    out["charge_missed"] = bool(out["status"] == "ok"
                                and off_charge(out["delta_Eb_J"], float(vp.E_b_max)))
    # the last plan's Level 2 flags by name (None: a strategy without the iteration's Level 2)
    level2 = out["level2_status"] = level2_names(out["level2_status"])
    eco = None
    if res.strategy == "multilevel-eco":  # what sizes and explains an eco-trip-time-missed
        from .levels.velocity import eco_status_names

        eco = {"eco_lambda_t": float(res.extra.lambda_t),
               "eco_level3_trip_time_s": float(res.extra.level3_trip_time),
               "eco_status": eco_status_names(int(res.extra.eco_status))}
        out |= eco
    write_run_files(res, vp, csv, plot)
    if args.json:
        print(json.dumps(_json_safe(out)))
        return 0
    rows = [("route", f"{out['route']} ({path})"), ("strategy", out["strategy"]),
            ("vehicle", f"{args.vehicle}, {out['mass_kg']:.0f} kg, "
                        f"battery {out['battery_MJ']:g} MJ")]
    if options:
        rows.append(("options", ", ".join(f"{k}={v}" for k, v in options.items())))
    for key, label, unit, scale, fmt in SIMULATE_ROWS:
        v = out[key]
        text = str(v) if scale is None else format(v * scale, fmt)
        if key == "delta_Eb_J":  # the charge-sustaining check reads it against the battery
            unit += f" ({100 * v / (out['battery_MJ'] * 1e6):+.2f} % of the battery)"
            if out["charge_missed"]:
                unit += f"; beyond {100 * CHARGE_SHARE:g} %: not charge sustaining"
        why = no_trip_time(out["status"]) if key == "trip_time_s" else None
        if why is not None:
            text, unit = "-", f"({why})"
        elif key == "trip_time_s":  # against the Level 3 prediction the run followed
            t3 = out["level3_trip_time_s"]
            unit += (f" (Level 3: {t3:.1f} s, {float(trip_vs_level3_pct(v, t3)):+.2f} %)"
                     if t3 > 0 else "")
        rows.append((label, f"{text} {unit}".rstrip()))
    if level2 is not None:
        hint = " (more pieces: --option l2_pieces=N)" if "pieces-exhausted" in level2 else ""
        rows.append(("Level 2 (last plan)", (", ".join(level2) or "converged") + hint))
    if eco is not None:
        rows.append(("eco-driving", f"lambda_t {eco['eco_lambda_t']:.0f} J/s, Level 3's own trip "
                                    f"{eco['eco_level3_trip_time_s']:.1f} s, "
                                    f"{', '.join(eco['eco_status']) or 'target met'}"))
    rows += [(label, str(p)) for label, p in (("time series", csv), ("plot", plot))
             if p is not None]
    _print_table(rows)
    return 0


def register_simulate(sub) -> None:
    p = sub.add_parser(
        "simulate",
        help="simulate one energy-management strategy on a route",
        description=cmd_simulate.__doc__,
    )
    _run_args(p)
    p.add_argument("--strategy", default="multilevel", metavar="NAME",
                   help="conventional, baseline, multilevel (default), multilevel-mpc, "
                        "dp-bound, multilevel-eco")
    p.add_argument("--n-iter", dest="n_iter", type=whole_number, default=None, metavar="N",
                   help="multilevel iterations (default 2)")
    p.add_argument("--csv", metavar="FILE",
                   help="write the plant's time series (t, s, v, v_ref, E_b, mode, gear, powers, "
                        "lambda_b), a row a step")
    p.add_argument("--plot", metavar="FILE",
                   help="write the run's traces over distance (P_d and P_m, mode, gear, E_b, v) "
                        "as a PNG")
    p.set_defaults(func=cmd_simulate)


# ---------------------------------------------------------------------------------- compare
# (JSON key, column head, format of the value) of the human-readable `compare` table
COMPARE_COLUMNS = [
    ("fuel_J", "fuel MJ", "9.3f", 1e-6),
    ("fuel_l_per_100km", "l/100km", "8.2f", 1.0),
    ("delta_Eb_J", "dE_b MJ", "+8.3f", 1e-6),
    ("fuel_corrected_J", "corr. MJ", "9.3f", 1e-6),
    ("fuel_corrected_l_per_100km", "corr. l/100km", "13.2f", 1.0),
    ("saving_vs_conventional_pct", "vs conv. %", "10.1f", 1.0),
    ("saving_vs_baseline_pct", "vs base. %", "10.1f", 1.0),
    ("trip_time_s", "trip s", "8.1f", 1.0),
    ("wall_s", "wall s", "7.1f", 1.0),
]


def cmd_compare(args) -> int:
    """`jaxems compare`: several energy-management strategies on one route and one vehicle.

    Prints each strategy's fuel (MJ and l/100 km), its battery balance, its fuel corrected for
    the battery energy left over (fuel + lambda_b dE_b, as sweeps correct it) and its saving on
    corrected fuel against the conventional truck and the A-ECMS baseline (positive = less
    fuel), the runs one after the other.
    """
    from .io import resolve_route
    from .strategies import check_strategy, level2_names
    from .sweep import compare_strategies, option_pairs

    strategies = [check_strategy(s) for s in comma_list(args.strategies)]
    traces = check_output(args.traces, "--traces", directory=True)  # before any run
    if traces is not None:  # the files it writes there
        check_not_inputs([("--traces", traces / f"{s}{ext}") for s in strategies
                          for ext in (".csv", ".png")], args.route, args.vehicle)
    _setup_jax()
    vp = _load_vehicle(args)
    path = resolve_route(args.route)
    options = option_pairs(args.option, strategy=strategies)

    def progress(row):
        if not args.json:
            print(f"  {row['strategy']:<15} {row['wall_s']:6.1f} s", file=sys.stderr, flush=True)

    def files(res):  # each run's time series and traces, as simulate --csv / --plot write them
        if traces is not None:
            traces.mkdir(exist_ok=True)  # once the runs have started: their input is good
            write_run_files(res, vp, traces / f"{res.strategy}.csv",
                            traces / f"{res.strategy}.png")

    rows = compare_strategies(str(path), vp, strategies, dt=args.dt, progress=progress,
                              on_result=files, **options)
    out = {"route": rows[0]["route"], "file": str(path), "vehicle": str(args.vehicle),
           "mass_kg": float(vp.mass), "battery_MJ": float(vp.E_b_max) / 1e6,
           "initial_soc": float(vp.soc0), "dt_s": float(args.dt), "options": options,
           "rows": [_json_safe(r | {"level2_status": level2_names(r["level2_status"])})
                    for r in rows]}
    if args.json:
        print(json.dumps(out))
        return 0
    print(f"route    {out['route']} ({path}), {rows[0]['length_m'] / 1000:.3f} km")
    print(f"vehicle  {args.vehicle}, {out['mass_kg']:.0f} kg, battery {out['battery_MJ']:g} MJ "
          f"starting at {100 * out['initial_soc']:g} %"
          + (", options " + ", ".join(f"{k}={v}" for k, v in options.items()) if options else ""))
    head = f"{'strategy':<15}" + "".join(f" {h:>{len(format_or_dash(None, f))}}"
                                          for _, h, f, _ in COMPARE_COLUMNS)
    print(head + "  status")
    print("-" * (len(head) + 8))
    whys = []  # why a trip time is '-', in simulate's words (on a route Level 3 predicts the
    # truck cannot climb, a baseline's trip up it with its motor's help showed 97.9 s)
    for r in rows:
        why = no_trip_time(r["status"])
        if why is not None and why not in whys:
            whys.append(why)
        cells = "".join(" " + format_or_dash(
            None if r[k] is None or (k == "trip_time_s" and why) else r[k] * scale, f)
            for k, _, f, scale in COMPARE_COLUMNS)
        flag = " *" if r["charge_missed"] else ""
        print(f"{r['strategy']:<15}{cells}  {r['status']}{flag}")
    print("corr. = fuel + lambda_b dE_b (the run's first Level 2 costate); savings on corr.; "
          "- where the reference was not run or a run is not ok")
    for why in whys:
        print(f"- trip s: {why}")
    if any(r["charge_missed"] for r in rows):
        print("* the battery ends more than 1 % of its size from where it started: "
              "not charge sustaining")
    if traces is not None:
        print(f"traces   {traces}/STRATEGY.csv and .png")
    return 0


def register_compare(sub) -> None:
    p = sub.add_parser(
        "compare",
        help="several strategies on one route: fuel and savings",
        description=cmd_compare.__doc__,
    )
    _run_args(p)
    p.add_argument("--strategies", default="conventional,baseline,multilevel", metavar="A,B,...",
                   help="comma-separated strategies (default conventional,baseline,multilevel; "
                        "also multilevel-mpc, dp-bound, multilevel-eco)")
    p.add_argument("--traces", metavar="DIR",
                   help="write each strategy's time series and traces to DIR/STRATEGY.csv and "
                        ".png (as simulate --csv and --plot); DIR is made if missing, in an "
                        "existing directory")
    p.set_defaults(func=cmd_compare)


def _run_args(p) -> None:
    """The arguments `simulate` and `compare` share: the route, the vehicle and its overrides,
    the time step, strategy options, --json."""
    p.add_argument("route", metavar="ROUTE", help=".vdri or .csv file, or a bundled route name")
    _common_vehicle(p)
    p.add_argument("--battery-MJ", dest="battery_MJ", type=number, default=None, metavar="X",
                   help="usable battery energy in MJ (overrides the vehicle file)")
    p.add_argument("--initial-soc", dest="initial_soc", type=number, default=None, metavar="F",
                   help="starting charge, a fraction of the battery in [0, 1] (overrides the "
                        "vehicle file)")
    p.add_argument("--dt", type=number, default=1.0, help="time step in s, 0.05 to 10 (default 1)")
    p.add_argument("--option", action="append", default=[], metavar="NAME=VALUE",
                   help="a strategy option (a field of jaxems.strategies.Options, as a sweep "
                        "file's [options] table sets it; VALUE in TOML: sustain=false, "
                        "l2_pieces=64); repeatable")
    p.add_argument("--json", action="store_true", help="print one JSON object")


def _common_vehicle(p) -> None:
    p.add_argument(
        "--vehicle",
        default="reference_truck",
        metavar="NAME|PATH",
        help="bundled vehicle name or TOML file (default reference_truck)",
    )
    p.add_argument(
        "--mass",
        type=number,
        default=None,
        metavar="KG",
        help="vehicle mass in kg (overrides the vehicle file)",
    )


# --------------------------------------------------------------------------------- main
def register_sweep(sub) -> None:
    from .sweep import register_sweep as reg

    reg(sub)


def register_report(sub) -> None:
    from .report import register_report as reg

    reg(sub)


SUBCOMMANDS: list[Callable] = [register_route, register_predict, register_simulate,
                               register_compare, register_sweep, register_report]


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with one subparser per entry of `SUBCOMMANDS`."""
    parser = argparse.ArgumentParser(
        prog="jaxems",
        description="Multi-level predictive energy management for hybrid trucks, in JAX.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for register in SUBCOMMANDS:
        register(sub)
    return parser


def print_result(name: str, compute, as_json: bool, fmt) -> int:
    """The experiment scripts' ending: out = compute(), printed as one JSON object (as_json)
    or as fmt(out); a bad input (ValueError, OSError: route, vehicle and option errors) is one
    line `NAME: error: ...` on stderr and exit status 1."""
    def run():
        out = compute()
        print(json.dumps(out) if as_json else fmt(out))

    return script_main(name, run)


def out_of_memory(e: BaseException) -> str | None:
    """Where e is the machine running out of memory (Python's MemoryError, or XLA's
    RESOURCE_EXHAUSTED: a `jax.errors.JaxRuntimeError`, told by name: no JAX import here), the
    first line of its message, in one line; else None."""
    if not (isinstance(e, MemoryError) or (type(e).__name__ == "JaxRuntimeError"
                                           and "RESOURCE_EXHAUSTED" in str(e))):
        return None
    return " ".join(str(e).split("\n")[0].split())[:200]


OUT_OF_MEMORY_HINT = ("out of memory; a shorter route, a larger time step (--dt), fewer "
                      "configurations at once (a sweep's chunk) or smaller size options "
                      "(dp_n_E, l2_pieces, h2) need less")


def script_main(name: str, main, *args) -> int:
    """The entry of `jaxems` and of the experiments and benchmarks: main(*args), its exit
    status; a bad input (ValueError, OSError, CLIError: route, vehicle, option and argument
    errors) is one line `NAME: error: ...` on stderr and exit status 1, not a traceback, and so
    is a run that does not fit in the machine's memory (`out_of_memory`), with what shrinks it."""
    try:
        return int(main(*args) or 0)
    except (ValueError, OSError, CLIError) as e:  # RouteError, VehicleError are ValueErrors
        print(f"{name}: error: {' '.join(str(e).split())}", file=sys.stderr)
        return EXIT_ERROR
    except (MemoryError, RuntimeError) as e:
        cause = out_of_memory(e)
        if cause is None:
            raise
        print(f"{name}: error: {OUT_OF_MEMORY_HINT} ({cause})", file=sys.stderr)
        return EXIT_ERROR


def number(text: str) -> float:
    """argparse type: a finite number (a mass, a battery size, a time step)."""
    return _strict(text, float, "a finite number")


def whole_number(text: str) -> int:
    """argparse type: a whole number (a count of iterations, workers or devices)."""
    return _strict(text, int, "a whole number")


def positive_int(text: str) -> int:
    """argparse type: a whole number >= 1 (a batch, a count of repeats or steps)."""
    return _positive(text, int, "a whole number >= 1")


def positive_float(text: str) -> float:
    """argparse type: a finite number > 0 (a mass, a speed, a time)."""
    return _positive(text, float, "a finite number > 0")


def _positive(text: str, cast, what: str):
    x = _strict(text, cast, what)
    if not x > 0:
        raise argparse.ArgumentTypeError(f"expected {what} (got {text})")
    return x


def _strict(text: str, cast, what: str):
    """`text` read by `cast` where it is a finite number written as a route file's cell is
    (`io._table._NUMBER`: ASCII digits with a point and an exponent), else argparse's error,
    which names the option. float() and int() alone also read 20_000, other scripts' digits
    (a full-width 20000) and, float(), nan and inf, which route files refuse."""
    from .io._table import _NUMBER

    if not _NUMBER.fullmatch(text.strip()):
        raise argparse.ArgumentTypeError(f"expected {what} in ASCII digits, as route files "
                                         f"write numbers (got {text!r})")
    try:
        x = cast(text)
    except ValueError:  # int("2.5")
        raise argparse.ArgumentTypeError(f"expected {what} (got {text!r})") from None
    if not math.isfinite(x):
        raise argparse.ArgumentTypeError(f"expected {what} (got {text})")
    return x


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit status (0 ok, 1 bad input, 2 bad usage)."""
    args = build_parser().parse_args(argv)
    try:
        return script_main("jaxems", args.func, args)
    except KeyboardInterrupt:  # Ctrl-C: a line, not JAX's traceback; files are whole or absent
        hint = ("; finished chunks are kept: run it again with --resume to go on"
                if args.command == "sweep" else "")
        print(f"jaxems: interrupted{hint}", file=sys.stderr)
        return EXIT_INTERRUPTED


def run() -> None:
    """The process's entry (the `jaxems` script, `python -m jaxems`): `main`'s status as the
    process's exit status. After Ctrl-C the process ends at once (`os._exit`, its streams
    flushed): main has printed its line and unwound (files whole or absent, a sweep's lock
    released), but XLA's compiler threads may still be running, and the interpreter's teardown
    under them crashed (status 139 in 2 of 3 tries interrupted during a compilation)."""
    status = main()
    if status == EXIT_INTERRUPTED:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(status)
    sys.exit(status)


if __name__ == "__main__":
    run()
