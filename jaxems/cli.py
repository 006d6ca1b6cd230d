"""The `jaxems` command line (also `python -m jaxems`).

    jaxems route ROUTE [--json]                          facts of a route file
    jaxems predict ROUTE [--vehicle NAME|PATH] [--mass KG] [--json] [--csv FILE]
                                                         Level 3 speed and power prediction

ROUTE is a `.vdri` or `.csv` file or the name of a bundled route (``short_track``,
``LongHaul``, ...). A bad file or value prints one line on stderr and exits with status 1.

Each subcommand is a `register_*` function that adds its parser and sets ``func``; new
subcommands (simulate, sweep, report) add one more `register_*` to `SUBCOMMANDS`.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Sequence

from .params import VehicleError
from .route import RouteError

EXIT_ERROR = 1


class CLIError(Exception):
    """A user-facing error: printed as one line, exit status 1."""


def _enable_x64() -> None:
    import jax

    jax.config.update("jax_enable_x64", True)


def _load_vehicle(args):
    from .params import load_vehicle, with_overrides

    vp = load_vehicle(args.vehicle)
    return with_overrides(vp, mass_kg=args.mass)


def _load(args):
    from .io import load_route, resolve_route, route_name

    path = resolve_route(args.route)
    return route_name(path), path, load_route(path, ds=args.ds)


def _print_table(pairs: list[tuple[str, str]]) -> None:
    w = max(len(k) for k, _ in pairs)
    for k, v in pairs:
        print(f"{k:<{w}}  {v}")


# ------------------------------------------------------------------------------------ route
def cmd_route(args) -> int:
    """`jaxems route`: length, duration at the predicted speed, gradient range, stops."""
    from .levels.velocity import predict_velocity
    from .route import route_summary

    _enable_x64()
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
    p.add_argument("--ds", type=float, default=10.0, help="distance grid step in m (default 10)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=cmd_route)


# ---------------------------------------------------------------------------------- predict
def cmd_predict(args) -> int:
    """`jaxems predict`: Level 3 speed and driveline power prediction over a route."""
    import numpy as np

    from .levels.velocity import energy_summary, predict_velocity

    _enable_x64()
    name, path, route = _load(args)
    vp = _load_vehicle(args)
    pred = predict_velocity(route, vp, dt=args.dt)
    out = {
        "route": name,
        "file": str(path),
        "vehicle": str(args.vehicle),
        "mass_kg": float(vp.mass),
        "dt_s": args.dt,
    } | energy_summary(pred)
    if args.csv:
        m = np.asarray(pred.mask)
        cols = [np.asarray(x)[m] for x in (pred.t, pred.s, pred.v, pred.a, pred.grade, pred.P_d)]
        with open(args.csv, "w", encoding="utf-8") as fh:
            fh.write("t_s,s_m,v_m_s,a_m_s2,grade,P_d_W\n")
            for row in zip(*cols, strict=True):
                fh.write(",".join(f"{x:.6g}" for x in row) + "\n")
    if args.json:
        print(json.dumps(out))
        return 0
    _print_table(
        [
            ("route", f"{name} ({path})"),
            ("vehicle", f"{args.vehicle}, {out['mass_kg']:.0f} kg"),
            ("trip time", f"{out['trip_time_s']:.1f} s ({out['steps']} steps of {args.dt:g} s)"),
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
    p.add_argument("--dt", type=float, default=1.0, help="time step in s (default 1)")
    p.add_argument("--ds", type=float, default=10.0, help="distance grid step in m (default 10)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--csv", metavar="FILE", help="write the time series (t, s, v, a, grade, P_d)")
    p.set_defaults(func=cmd_predict)


def _common_vehicle(p) -> None:
    p.add_argument(
        "--vehicle",
        default="reference_truck",
        metavar="NAME|PATH",
        help="bundled vehicle name or TOML file (default reference_truck)",
    )
    p.add_argument(
        "--mass",
        type=float,
        default=None,
        metavar="KG",
        help="vehicle mass in kg (overrides the vehicle file)",
    )


# --------------------------------------------------------------------------------- main
SUBCOMMANDS: list[Callable] = [register_route, register_predict]


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


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit status (0 ok, 1 bad input, 2 bad usage)."""
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (RouteError, VehicleError, CLIError, ValueError, OSError) as e:
        msg = " ".join(str(e).split())
        print(f"jaxems: error: {msg}", file=sys.stderr)
        return EXIT_ERROR


if __name__ == "__main__":
    sys.exit(main())
