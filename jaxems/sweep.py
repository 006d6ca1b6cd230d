"""Fleet sweeps: routes x vehicle-parameter grids x strategies, batched, resumable, distributed.

    jaxems sweep SWEEP.toml [--out DIR] [--workers N | --scheduler ADDRESS] [--resume] [--quiet]

The sweep file (TOML) names route files or globs, a vehicle, strategies and a grid over vehicle
parameters; see `load_config` for the keys and `examples/` for examples. The grid is the
Cartesian product of the listed values (first key slowest).

Execution. The work is cut into chunks: (route, strategy, `batch_size` consecutive grid points).
Each chunk is one call of `jaxems.strategies.simulate_batch` on a vehicle batch of exactly
`batch_size` members, or of the grid's size where that is smaller (the last chunk of a route
repeats its last point; the padding rows are dropped), with the same static number of time
steps for every chunk of a route (the maximum over the route's whole grid, bucketed). So every
chunk of a (strategy, route shape) has the same shapes and the jitted kernels compile once per
(strategy, padded route length, step bucket), not once per chunk; new grid values never
recompile.

Nothing lost. Every finished chunk is written to ``DIR/chunks/<chunk id>.parquet`` atomically
(temporary file, fsync, rename). Chunk ids are deterministic (route index and name, strategy,
chunk index), so a rerun into the same directory (or ``--resume``) computes only the chunks
without a file. ``DIR/sweep.json`` holds the canonical sweep (parsed settings, route and
vehicle content hashes, the hash of jaxems's own code) and its fingerprint; a different sweep,
or the same one by other code, in the same directory is refused. At the end the chunks are
merged into ``DIR/results.parquet`` (see `load_sweep`) and the report is written
(`jaxems.report`).

Distributed. The default runs in-process. ``--workers N`` starts a local Dask cluster of N
single-threaded worker processes; ``--scheduler tcp://HOST:PORT`` sends the chunks to a running
Dask cluster (``dask scheduler`` / ``dask worker tcp://HOST:8786 --nthreads 1``). Each Dask task
is one chunk and returns its rows; the client writes the chunk files, so workers need no shared
file system. Workers keep their compiled kernels between tasks (module-level jit caches).

Precision: sweeps run in float32 unless the sweep file says ``precision = "float64"``; the
setting is applied around each chunk (in-process and on workers), so it does not leak.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
import glob
import hashlib
import itertools
import json
import math
import os
import re
import shutil
import sys
import threading
import time
import tomllib
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .params import (
    _SCHEMA,
    VehicleError,
    VehicleParams,
    check_number,
    check_vehicle,
    load_vehicle,
    read_toml,
)
from .report import CHARGE_SHARE, TRIP_SHARE, charge_missed, trip_long, write_report
from .route import DS_RANGE, Route, RouteError

FORMAT_VERSION = 1
BATCH_SIZE_MAX = 65536  # grid points a chunk at most (a chunk's arrays are padded to it)
# Grid points a sweep at most (per route and strategy; also the most values of one grid key).
# load_config builds every point (a dict each) and checks each point's vehicle: 1e6 points take
# seconds and a few hundred MB, 1e7 took 18 s and 3 GB, 1e8 did not end. And 1e6 configurations
# are already days of computing at the tens to hundreds of configurations per second a sweep
# runs at; a larger study is several sweeps.
GRID_MAX = 1_000_000
# --devices at most (in-process sweeps; unless the machine has more cores). XLA's CPU client
# runs every device's share on its own thread and meets them all at each collective: with 1000
# devices that rendezvous stalled and XLA aborted the process (SIGABRT after 70 s of warnings),
# 256 ran on a 2-core machine. More devices than cores gain nothing but smaller shares anyway.
DEVICES_MAX = 256
CONFIG_FILE = "sweep.json"
SOURCE_COPY = "sweep.toml"
CHUNK_DIR = "chunks"
RESULTS_FILE = "results.parquet"

# Fields of `jaxems simulate --json` that `simulate_batch` returns (float unless noted).
RESULT_FIELDS = (
    "length_m", "trip_time_s", "level3_trip_time_s", "fuel_J", "fuel_l_per_100km",
    "delta_Eb_J", "Eb_min_J", "Eb_max_J", "mode_switches", "gear_switches", "lambda_b",
    "max_speed_shortfall_mps", "level2_status",
)
# level2_status: the last plan's Level 2 flags as an integer (`strategies.level2_names`;
# `strategies.NO_LEVEL2`: the strategy has none, and a chunk that failed)
INT_FIELDS = ("mode_switches", "gear_switches", "level2_status")
# Reference strategies for the savings columns.
REFERENCES = ("conventional", "baseline")
# Strategies without a battery: their fuel needs no correction for a battery energy change.
NO_BATTERY = ("conventional",)

# User-facing grid keys (units in the name) -> (VehicleParams field, scale to SI, check).
GRID_KEYS: dict[str, tuple[str, float, str]] = {
    "mass_kg": ("mass", 1.0, "mass"),
    "battery_MJ": ("E_b_max", 1e6, "pos"),
    "motor_power_kW": ("pm_max", 1e3, "motor"),
    "motor_torque_Nm": ("tm_max", 1.0, "motor"),
    "beta_per_W": ("beta", 1.0, "beta"),
    "engine_efficiency": ("eta_e", 1.0, "frac"),
    "initial_soc": ("soc0", 1.0, "unit"),
}
# The VehicleParams fields that a user key sets, by field: the key (a raw name for them would
# leave the results' mass_kg and battery_MJ columns, which the report reads, at the vehicle
# file's values)
USER_KEY = {field: key for key, (field, _, _) in GRID_KEYS.items()}
# Checks of the raw VehicleParams fields (by their own names, in SI), from the vehicle file
# schema; the cruise speed's rule reads km/h, the file's unit: a raw v_cruise (m/s) is checked
# positive here and against the rule by `check_vehicle`, which every grid point's vehicle meets
# (`_check_grid_vehicles`). has_motor: a hybrid or not, 1 or 0 (the plant reads > 0.5, the
# powertrain scales the motor by it).
_FIELD_CHECK = {field: "pos" if kind == "cruise" else kind
                for (field, _, kind) in _SCHEMA.values() if not field.startswith("_")}
_FIELD_CHECK["has_motor"] = "zero_one"

TOP_KEYS = {
    "description": "free text, kept in the results directory",
    "routes": "route files, globs or bundled route names (list)",
    "vehicle": "bundled vehicle name or TOML file (default reference_truck)",
    "strategies": "strategies to run (list)",
    "grid": "table: parameter = [values]",
    "batch_size": "grid points per chunk (default 16)",
    "dt_s": "time step in s (default 1)",
    "ds_m": "distance grid step of the routes in m (default 10)",
    "precision": '"float32" (default) or "float64"',
    "options": "table: strategy = {options passed to simulate_batch}",
}


class SweepError(ValueError):
    """A bad sweep file, grid value, route, or results directory; the message names it."""


# ------------------------------------------------------------------------------------ config
@dataclasses.dataclass(frozen=True)
class RouteEntry:
    """A route of the sweep: display name, file, content hash and the loaded `Route`."""

    name: str
    path: Path
    sha256: str
    route: Route


@dataclasses.dataclass(frozen=True)
class SweepConfig:
    """A validated sweep: everything needed to plan and run it (see `load_config`)."""

    source: Path
    text: str
    description: str
    routes: tuple[RouteEntry, ...]
    vehicle_spec: str
    vehicle_sha256: str
    vehicle: VehicleParams
    strategies: tuple[str, ...]
    grid: dict[str, tuple[float, ...]]  # user key -> values (user units), file order
    batch_size: int
    dt: float
    ds: float
    precision: str
    options: dict[str, dict]

    @property
    def grid_size(self) -> int:
        return math.prod(len(v) for v in self.grid.values())

    def points(self) -> list[dict[str, float]]:
        """The grid points in order (first key slowest), as {user key: value}."""
        return _grid_points(self.grid)

    def canonical(self) -> dict:
        """What identifies the sweep's results: settings and route/vehicle contents, no paths."""
        return {
            "format": FORMAT_VERSION,
            "routes": [{"name": r.name, "sha256": r.sha256} for r in self.routes],
            "vehicle": {"name": Path(self.vehicle_spec).stem, "sha256": self.vehicle_sha256},
            "strategies": list(self.strategies),
            "grid": {k: list(v) for k, v in self.grid.items()},
            # the keys' order sets the points' order (first key slowest), which the chunks'
            # grid_index reads; the fingerprint sorts the table's keys
            "grid_order": list(self.grid),
            "batch_size": self.batch_size,
            "dt_s": self.dt,
            "ds_m": self.ds,
            "precision": self.precision,
            "options": self.options,
            "code": code_sha256(),
        }

    def fingerprint(self) -> str:
        blob = json.dumps(self.canonical(), sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(blob.encode()).hexdigest()


def _grid_points(grid: dict[str, tuple[float, ...]]) -> list[dict[str, float]]:
    keys = list(grid)
    return [dict(zip(keys, vals, strict=True)) for vals in itertools.product(*grid.values())]


def _check_grid_vehicles(vehicle: VehicleParams, grid: dict[str, tuple[float, ...]]) -> None:
    """Every grid point's vehicle against the rules `check_vehicle` holds (those across fields
    too: the engine's speed range); only the grid's fields get a batch axis."""
    check_vehicle(vehicle._replace(**_grid_leaves(_grid_points(grid))))


def _sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


@functools.lru_cache(maxsize=1)
def code_sha256() -> str:
    """Content hash of jaxems's own source (every ``.py`` file of the package, by relative
    path): results computed by other code are not mixed into a sweep (an upgrade, or an edit
    of a development install, changes it)."""
    root = Path(__file__).resolve().parent
    h = hashlib.sha256()
    for f in sorted(root.rglob("*.py")):
        h.update(f.relative_to(root).as_posix().encode() + b"\0" + f.read_bytes() + b"\0")
    return h.hexdigest()


def grid_field(key: str) -> tuple[str, float, str]:
    """(VehicleParams field, scale to SI, check) of a grid key; `SweepError` if unknown."""
    if key in GRID_KEYS:
        return GRID_KEYS[key]
    if key in VehicleParams._fields:
        return key, 1.0, _FIELD_CHECK.get(key, "finite")
    raise KeyError(key)


def _check_value(x: Any, kind: str, where: str) -> float:
    return check_number(x, kind, where, SweepError)


def _grid_values(spec: Any, where: str) -> list:
    """A list of numbers, one number, or {start, stop, num} (evenly spaced, both ends)."""
    if isinstance(spec, dict):
        extra = set(spec) - {"start", "stop", "num"}
        if extra or {"start", "stop", "num"} - set(spec):
            raise SweepError(f"{where}: a range needs exactly start, stop and num "
                             f"(got {sorted(spec)})")
        num = spec["num"]
        if isinstance(num, bool) or not isinstance(num, int) or num < 1:
            raise SweepError(f"{where}.num: must be a whole number >= 1 (got {num!r})")
        if num > GRID_MAX:  # before the values are made: 1e8 of them did not end
            raise SweepError(f"{where}.num: at most {GRID_MAX} values (got {num})")
        for k in ("start", "stop"):
            if isinstance(spec[k], bool) or not isinstance(spec[k], int | float):
                raise SweepError(f"{where}.{k}: expected a number (got {spec[k]!r})")
        return [float(x) for x in np.linspace(spec["start"], spec["stop"], num)]
    if isinstance(spec, list):
        return spec
    return [spec]


def _check_precision(values: Any, scale: float, precision: str, where: str,
                     indexed: bool = True) -> None:
    """Each of `values` (user units; times `scale` in SI, as a chunk's vehicle holds them)
    as JAX computes in `precision`: finite and, where not 0, at least the smallest normal
    number (float32 holds magnitudes from 1.2e-38 to 3.4e38; XLA's CPU code flushes smaller
    ones to 0). Else `SweepError` naming `where` (with the value's index where `indexed`):
    float64 checks alone let float32 sweeps overflow into NaN results."""
    user = np.ravel(np.asarray(values, dtype=np.float64))
    si = user * scale
    with np.errstate(over="ignore", under="ignore"):
        held = si.astype(precision)
    tiny, big = np.finfo(precision).tiny, np.finfo(precision).max
    bad = np.flatnonzero(~np.isfinite(held) | ((si != 0) & (np.abs(held) < tiny)))
    if bad.size:
        i = int(bad[0])
        hint = '; precision = "float64" holds more' if precision == "float32" else ""
        raise SweepError(f"{where}{f'[{i}]' if indexed else ''}: {user[i]:g} is beyond what "
                         f"{precision} holds (magnitudes {tiny / scale:.3g} to "
                         f"{big / scale:.3g}, or 0){hint}")


def _resolve_routes(entries: Any, base: Path, where: str, ds: float) -> tuple[RouteEntry, ...]:
    from .io import load_route, resolve_route, route_name

    if isinstance(entries, str):
        entries = [entries]
    if not isinstance(entries, list) or not entries:
        raise SweepError(f"{where}: routes must be a non-empty list of files, globs or names")
    paths: list[Path] = []
    for e in entries:
        if not isinstance(e, str) or not e.strip():
            raise SweepError(f"{where}: routes: expected a file, glob or name (got {e!r})")
        pat = Path(e).expanduser()
        if not pat.is_absolute():
            pat = base / pat
        if any(c in e for c in "*?["):
            found = sorted(Path(p) for p in glob.glob(str(pat), recursive=True))
            found = [p for p in found if p.is_file()]
            if not found:
                raise SweepError(f"{where}: routes: {e!r} matches no file")
            paths.extend(found)
        elif pat.exists():
            paths.append(pat)
        else:
            try:
                p = resolve_route(e)
            except RouteError:
                raise SweepError(f"{where}: routes: {e!r}: no such route file (not at {pat}, "
                                 f"nor a bundled route)") from None
            if not p.exists():
                raise SweepError(f"{where}: routes: {e!r}: no such route file (looked at {pat})")
            paths.append(p)
    out: list[RouteEntry] = []
    seen: dict[str, Path] = {}  # by the name in file names: "x y" and "x_y" would share them
    for p in paths:
        p = p.resolve()
        name = route_name(p)
        key = safe_name(name)
        if key in seen:
            if seen[key] == p:
                continue  # listed twice (e.g. a name and a glob): once is enough
            raise SweepError(f"{where}: routes: two route files named {name!r} or alike (as "
                             f"{key!r} in file names): {seen[key]} and {p}; rename one")
        if len(key) > NAME_MAX:
            raise SweepError(f"{where}: routes: {p}: a name of {len(key)} characters; at most "
                             f"{NAME_MAX} (the results' file names carry it): rename the file")
        seen[key] = p
        try:
            route = load_route(p, ds=ds)
        except RouteError as e:
            raise SweepError(f"{where}: routes: {e}") from None
        out.append(RouteEntry(name=name, path=p, sha256=_sha256(p), route=route))
    return tuple(out)


def load_config(path: str | Path) -> SweepConfig:
    """Read and validate a sweep file; every problem is a `SweepError` naming the key/file.

    Keys (top level of the TOML file):

    - ``routes``: list of route files, globs (``**`` recursive; relative to the sweep file) or
      bundled route names; every file is read and checked now.
    - ``vehicle``: bundled vehicle name or TOML path (relative to the sweep file); default
      ``reference_truck``.
    - ``strategies``: list of `jaxems.strategies.STRATEGIES`.
    - ``[grid]``: ``key = [values]`` (or one value, or ``{start, stop, num}``). Keys: see
      `GRID_KEYS` (mass_kg, battery_MJ, motor_power_kW, motor_torque_Nm, beta_per_W,
      engine_efficiency, initial_soc) or any scalar `VehicleParams` field by its own (SI) name.
    - ``batch_size`` (16), ``dt_s`` (1.0), ``ds_m`` (10.0), ``precision`` ("float32"),
      ``description``, ``[options.STRATEGY]`` (passed to `simulate_batch` as ``options``).
    """
    from .strategies import STRATEGIES, check_dt

    src = Path(path)
    if src.is_dir():
        raise SweepError(f"{path}: a directory, not a sweep file")
    if not src.is_file():
        raise SweepError(f"{path}: no such sweep file")
    text, doc = read_toml(src, SweepError)
    unknown = [k for k in doc if k not in TOP_KEYS]
    if unknown:
        raise SweepError(f"{src}: unknown key {unknown[0]!r} (known keys: "
                         f"{', '.join(TOP_KEYS)})")
    base = src.resolve().parent

    def number(key, default, kind, typ=float):
        x = doc.get(key, default)
        if typ is int and (isinstance(x, bool) or not isinstance(x, int)):
            raise SweepError(f"{src}: {key}: expected a whole number (got {x!r})")
        return typ(_check_value(x, kind, f"{src}: {key}"))

    batch_size = number("batch_size", 16, "pos", int)
    if batch_size > BATCH_SIZE_MAX:
        raise SweepError(f"{src}: batch_size: at most {BATCH_SIZE_MAX} grid points a chunk "
                         f"(got {batch_size})")
    dt = number("dt_s", 1.0, "pos")
    try:
        dt = check_dt(dt)
    except ValueError as e:
        raise SweepError(f"{src}: dt_s: {str(e).removeprefix('dt: ')}") from None
    ds = number("ds_m", 10.0, "pos")
    if not DS_RANGE[0] <= ds <= DS_RANGE[1]:  # here, not as if a route file were wrong
        raise SweepError(f"{src}: ds_m: must be from {DS_RANGE[0]:g} to {DS_RANGE[1]:g} m "
                         f"(got {ds:g})")
    precision = doc.get("precision", "float32")
    if precision not in ("float32", "float64"):
        raise SweepError(f"{src}: precision: expected \"float32\" or \"float64\" "
                         f"(got {precision!r})")
    description = doc.get("description", "")
    if not isinstance(description, str):
        raise SweepError(f"{src}: description: expected a string")

    # strategies (validated against the strategies module)
    strategies = doc.get("strategies")
    if isinstance(strategies, str):
        strategies = [strategies]
    if not isinstance(strategies, list) or not strategies:
        raise SweepError(f"{src}: strategies: expected a non-empty list (choose from "
                         f"{', '.join(STRATEGIES)})")
    for s in strategies:
        if s not in STRATEGIES:
            raise SweepError(f"{src}: strategies: unknown strategy {s!r} (choose from "
                             f"{', '.join(STRATEGIES)})")
    if len(set(strategies)) != len(strategies):
        raise SweepError(f"{src}: strategies: listed twice: "
                         f"{sorted({s for s in strategies if strategies.count(s) > 1})}")
    options = doc.get("options", {})
    if not isinstance(options, dict):
        raise SweepError(f"{src}: options: expected a table of [options.STRATEGY] tables")
    for k, v in options.items():
        if k not in strategies:
            raise SweepError(f"{src}: options.{k}: not one of the sweep's strategies "
                             f"({', '.join(strategies)})")
        if not isinstance(v, dict):
            raise SweepError(f"{src}: options.{k}: expected a table")
        strategy_options(v, f"{src}: options.{k}", strategy=k)

    # vehicle
    vspec = doc.get("vehicle", "reference_truck")
    if not isinstance(vspec, str):
        raise SweepError(f"{src}: vehicle: expected a name or a file (got {vspec!r})")
    vpath = Path(vspec).expanduser()
    if vpath.suffix and not vpath.is_absolute():
        vpath = base / vpath
    try:
        vehicle = load_vehicle(vpath if vpath.suffix else vspec)
    except VehicleError as e:
        raise SweepError(f"{src}: vehicle: {e}") from None
    from .params import VEHICLE_DIR

    vfile = vpath if vpath.suffix else VEHICLE_DIR / f"{vspec}.toml"

    # grid
    grid_doc = doc.get("grid")
    if not isinstance(grid_doc, dict) or not grid_doc:
        raise SweepError(f"{src}: grid: empty; give at least one parameter with values, e.g. "
                         f"[grid] mass_kg = [20000, 40000]")
    grid: dict[str, tuple[float, ...]] = {}
    grid_fields: set[str] = set()  # the vehicle fields the grid sets
    for key, spec in grid_doc.items():
        where = f"{src}: grid.{key}"
        if key in USER_KEY:
            raise SweepError(f"{where}: the vehicle's {key} is set by its grid key in user "
                             f"units, {USER_KEY[key]} (the results' columns and the report read "
                             f"it); use {USER_KEY[key]}")
        try:
            field, scale, kind = grid_field(key)
        except KeyError:
            fields = [f for f in VehicleParams._fields  # those a grid may set by name
                      if f not in USER_KEY and np.ndim(getattr(vehicle, f)) == 0]
            raise SweepError(f"{where}: unknown grid key {key!r} (known: "
                             f"{', '.join(GRID_KEYS)}, or a vehicle field: "
                             f"{', '.join(fields)})") from None
        if np.ndim(getattr(vehicle, field)) != 0:
            raise SweepError(f"{where}: {field} is a curve, not a number; it cannot be a grid "
                             f"parameter")
        grid_fields.add(field)
        values = _grid_values(spec, where)
        if not values:
            raise SweepError(f"{where}: empty list of values")
        vals = tuple(_check_value(x, kind, f"{where}[{i}]") for i, x in enumerate(values))
        if len(set(vals)) != len(vals):
            raise SweepError(f"{where}: a value is listed twice ({list(vals)})")
        _check_precision(vals, scale, precision, where)
        grid[key] = vals
    n_points = math.prod(len(v) for v in grid.values())
    if n_points > GRID_MAX:  # before any point is made
        raise SweepError(f"{src}: grid: {n_points} points ("
                         f"{' x '.join(f'{len(v)} {k}' for k, v in grid.items())}); at most "
                         f"{GRID_MAX} a sweep: split it into several sweeps")
    # the vehicle file's values too, as the chunks hold them (those the grid does not set)
    file_key = {field: (f"{section}.{key}", scale)
                for (section, key), (field, scale, _) in _SCHEMA.items()}
    for field, x in zip(VehicleParams._fields, vehicle, strict=True):
        if field not in grid_fields:
            name, scale = file_key.get(field, (field, 1.0))
            _check_precision(np.asarray(x) / scale, scale, precision,
                             f"{src}: vehicle: {name}", indexed=np.ndim(x) > 0)

    # every grid point's vehicle, as its chunk will build it: rules across fields (the
    # engine's speed range) and the grid's values against the vehicle file's
    try:
        _check_grid_vehicles(vehicle, grid)
    except VehicleError as e:
        raise SweepError(f"{src}: grid: {e}") from None

    routes = _resolve_routes(doc.get("routes"), base, str(src), ds)
    return SweepConfig(
        source=src, text=text, description=description, routes=routes,
        vehicle_spec=str(vspec), vehicle_sha256=_sha256(vfile), vehicle=vehicle,
        strategies=tuple(strategies), grid=grid, batch_size=batch_size, dt=dt, ds=ds,
        precision=precision, options={k: dict(v) for k, v in options.items()},
    )


def option_pairs(pairs, where: str = "--option", strategy=None) -> dict:
    """{name: value} from "NAME=VALUE" strings (VALUE a TOML value: `sustain=false`,
    `l2_pieces=64`), checked as a sweep file's options table is (`strategy_options`, for
    `strategy`: a name or a list).

    Raises `SweepError` naming the pair, or the option, that is bad (a value that is not one
    TOML value: "--option n_iter: not a valid value ('abc')")."""
    out = {}
    for pair in pairs:
        name, sep, value = pair.partition("=")
        try:
            if not sep or not name.strip():
                raise ValueError("expected NAME=VALUE")
            if name.strip() in out:  # the first would be dropped without a word
                raise ValueError(f"{name.strip()} given twice")
        except ValueError as e:
            raise SweepError(f"{where} {pair!r}: {e}") from None
        name, value = name.strip(), value.strip()
        try:  # one line: 'plant_extra=0.2\nend_cap=false' set end_cap in the TOML, dropped
            doc = None if "\n" in value or "\r" in value else tomllib.loads(f"v = {value}")
        except tomllib.TOMLDecodeError:  # its column counted the "v = " put before the value
            doc = None
        if doc is None or set(doc) != {"v"}:
            raise SweepError(f"{where} {name}: not a valid value ({value!r}; one TOML value "
                             f"on one line: 2, 0.5, true, \"text\")")
        out[name] = doc["v"]
    strategy_options(out, where, strategy)
    return out


def strategy_options(d: dict | None, where: str = "options", strategy=None):
    """`jaxems.strategies.Options` from a table of the sweep file (None: the defaults);
    strategy: the strategy (or a list of strategies) the table is for, if known.

    Raises `SweepError` naming the option for an unknown name, a bad value or, given
    `strategy`, an option that none of them depends on (`strategies.check_options_used`).
    """
    from . import strategies as st

    if not d:
        return None
    try:
        return st.make_options(d, strategy)
    except ValueError as e:
        raise SweepError(f"{where}: {e}") from None


# ------------------------------------------------------------------------------------ chunks
@dataclasses.dataclass(frozen=True)
class Chunk:
    """One unit of work: a route, a strategy and `batch_size` grid points (padded; the grid's
    size where that is smaller)."""

    id: str
    route_index: int
    strategy: str
    index: int  # chunk number within (route, strategy)
    grid_index: tuple[int, ...]  # (batch_size,) grid point indices, padded by repetition
    n_real: int  # the first n_real entries are real


def safe_name(name: str) -> str:
    """A route's name as it stands in file names (chunk files, report figures)."""
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name)


NAME_MAX = 100  # characters of a route's file name: a chunk file adds about 60, a file system
# allows 255


def plan_chunks(cfg: SweepConfig) -> list[Chunk]:
    """All chunks of a sweep, in execution order (route, strategy, grid chunk); ids stable."""
    # a grid smaller than batch_size is one chunk a route and strategy, all of one shape: no
    # need to pad it to batch_size (1 point with batch_size 4096 computed 4096 runs)
    G = cfg.grid_size
    B = min(cfg.batch_size, G)
    n_chunks = math.ceil(G / B)
    out = []
    for ri, r in enumerate(cfg.routes):
        for s in cfg.strategies:
            for c in range(n_chunks):
                idx = list(range(c * B, min((c + 1) * B, G)))
                n_real = len(idx)
                idx += [idx[-1]] * (B - n_real)
                out.append(Chunk(
                    id=f"r{ri:04d}-{safe_name(r.name)}--{s}--c{c:05d}", route_index=ri, strategy=s,
                    index=c, grid_index=tuple(idx), n_real=n_real,
                ))
    return out


def vehicle_batch(base: VehicleParams, points: Sequence[dict[str, float]]) -> VehicleParams:
    """A batch of len(points) vehicles: every leaf gets a leading axis; grid values set (SI)."""
    B = len(points)
    leaves = {f: np.array(np.broadcast_to(np.asarray(x, np.float64), (B, *np.shape(x))))
              for f, x in zip(VehicleParams._fields, base, strict=True)}
    return VehicleParams(**(leaves | _grid_leaves(points)))


def _grid_leaves(points: Sequence[dict[str, float]]) -> dict[str, np.ndarray]:
    """{VehicleParams field: (len(points),) its SI values} of the grid's keys."""
    out = {}
    for key in points[0]:
        field, scale, _ = grid_field(key)
        out[field] = np.array([p[key] * scale for p in points], dtype=np.float64)
    return out


@dataclasses.dataclass(frozen=True)
class ChunkTask:
    """What a worker needs for one chunk (plain arrays, picklable); the route goes separately."""

    chunk: Chunk
    vehicles: VehicleParams
    dt: float
    n_steps: int
    precision: str
    options: Any  # jaxems.strategies.Options or None


# Backend compilations seen by this process (a `jax.monitoring` listener; for the tests and the
# chunk statistics: chunks after the first of a shape must not compile).
_COMPILES = [0]
_COMPILES_LOCK = threading.Lock()
_LISTENING = [False]


def _on_event(event: str, *args, **kwargs) -> None:
    if event == "/jax/core/compile/backend_compile_duration":
        with _COMPILES_LOCK:
            _COMPILES[0] += 1


def compile_count() -> int:
    """Number of XLA backend compilations in this process since jaxems.sweep started counting."""
    if not _LISTENING[0]:
        import jax.monitoring

        jax.monitoring.register_event_duration_secs_listener(_on_event)
        _LISTENING[0] = True
    return _COMPILES[0]


@contextlib.contextmanager
def precision_scope(precision: str):
    """Run JAX in float32 or float64 inside the block (thread-local; restored afterwards)."""
    import jax

    with jax.enable_x64(precision == "float64"):
        yield


def compute_chunk(task: ChunkTask, route: Route) -> dict[str, Any]:
    """Evaluate one chunk: `simulate_batch` on its vehicle batch. Runs on any worker.

    Returns {field: (n_real,) array} with the `RESULT_FIELDS`, ``status`` and ``wall_s`` (the
    chunk's wall time per configuration), plus ``_compiles`` (backend compilations during the
    chunk in this process) and ``_wall_s`` (the chunk's wall time). An exception inside the
    strategy does not stop the sweep: every row of the chunk gets status ``error: ...`` (a
    chunk that does not fit in memory: what shrinks it).
    """
    from .strategies import NO_LEVEL2, simulate_batch

    c = task.chunk
    n = c.n_real
    c0 = compile_count()
    t0 = time.perf_counter()
    try:
        with precision_scope(task.precision):
            out = simulate_batch(route, task.vehicles, c.strategy, dt=task.dt,
                                 n_steps=task.n_steps, options=task.options)
        rows: dict[str, Any] = {}
        for f in RESULT_FIELDS:
            a = np.asarray(out[f])
            if a.shape[:1] != (len(c.grid_index),):
                raise ValueError(f"simulate_batch returned {f} of shape {a.shape}, expected "
                                 f"({len(c.grid_index)},)")
            rows[f] = a[:n].astype(np.int64 if f in INT_FIELDS else np.float64)
        rows["status"] = np.array([str(s) for s in np.asarray(out["status"])[:n]], dtype=object)
    except Exception as e:  # recorded per row; the sweep goes on
        from .cli import out_of_memory

        cause = out_of_memory(e)  # XLA's first line, and what shrinks the chunk
        text = (f"{type(e).__name__}: {e}" if cause is None else
                f"out of memory ({cause}); a smaller batch_size, a larger dt_s or smaller size "
                f"options need less")
        msg = " ".join(text.split())[:300]
        rows = {f: np.zeros(n, np.int64) if f in INT_FIELDS else np.full(n, np.nan)
                for f in RESULT_FIELDS}
        rows["level2_status"] = np.full(n, NO_LEVEL2, np.int64)
        rows["length_m"] = np.full(n, float(np.asarray(route.length)))
        rows["status"] = np.array([f"error: {msg}"] * n, dtype=object)
    wall = time.perf_counter() - t0
    rows["wall_s"] = np.full(n, wall / n)
    rows["_compiles"] = compile_count() - c0
    rows["_wall_s"] = wall
    return rows


def _compute_remote(task: ChunkTask, route: Route) -> dict[str, Any]:
    """Dask task body (module-level so that workers import it by name)."""
    _worker_cache()
    return compute_chunk(task, route)


def _worker_cache() -> None:
    """JAX's persistent compilation cache in a worker, from CACHE_ENV as `_executor` set it.
    JAX reads that variable when it is imported, and a worker spawned from the `jaxems`
    script imports JAX (re-importing the script) before Dask sets the worker's environment:
    without this the workers of `jaxems sweep --workers N` compiled every kernel anew."""
    import jax

    where = os.environ.get(CACHE_ENV)
    if where and not jax.config.jax_compilation_cache_dir:
        jax.config.update("jax_compilation_cache_dir", where)


def steps_for_route(cfg: SweepConfig, route: Route, chunks: Sequence[Chunk],
                    points: Sequence[dict]) -> int:
    """Static step count shared by all chunks of a route: max over its grid and strategies
    (bucketed; multilevel-eco drives its own profile, see `strategies.steps_for_batch`).

    Evaluated chunk by chunk on the same padded batches as the simulation (same shapes, so one
    Level 3 compilation per route shape).
    """
    from .strategies import Options, steps_for_batch

    eco = "multilevel-eco" in cfg.strategies
    eco_opts = (strategy_options(cfg.options.get("multilevel-eco")) or Options()) if eco else None

    seen: set[tuple[int, ...]] = set()
    n = 0
    with precision_scope(cfg.precision):
        for c in chunks:
            if c.grid_index in seen:
                continue
            seen.add(c.grid_index)
            vb = vehicle_batch(cfg.vehicle, [points[i] for i in c.grid_index])
            # multilevel-eco's count covers Level 3's (the other strategies') too
            n = max(n, int(steps_for_batch(route, vb, cfg.dt, "multilevel-eco" if eco else None,
                                           eco_opts)))
    return n


# ---------------------------------------------------------------------------- results dir
def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write `path` whole or not at all: a temporary file beside it, renamed over it (removed
    where the write fails or is interrupted)."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}-{threading.get_ident()}")
    try:
        with open(tmp, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


def _atomic_write_table(path: Path, df) -> None:
    import io

    buf = io.BytesIO()
    df.to_parquet(buf, index=False)
    atomic_write_bytes(path, buf.getvalue())


def _describe_change(old: dict, new: dict) -> str:
    keys = sorted(set(old) | set(new))
    diff = [k for k in keys if old.get(k) != new.get(k)]
    parts = []
    for k in diff:
        if k == "routes":
            o = {r["name"]: r["sha256"] for r in old.get(k, [])}
            n = {r["name"]: r["sha256"] for r in new.get(k, [])}
            changed = sorted(x for x in set(o) & set(n) if o[x] != n[x])
            added, gone = sorted(set(n) - set(o)), sorted(set(o) - set(n))
            bits = ([f"added {', '.join(added)}"] if added else []) + (
                [f"removed {', '.join(gone)}"] if gone else []) + (
                [f"file content changed: {', '.join(changed)}"] if changed else [])
            parts.append(f"routes ({'; '.join(bits) or 'order changed'})")
        elif k == "code":
            parts.append("code (computed by another version of jaxems)")
        elif k == "grid_order" and old.get("grid") == new.get("grid"):
            parts.append("the grid's key order (the first key varies slowest: a grid point's "
                         "index names another point)")
        else:
            parts.append(k)
    return ", ".join(parts)


def read_record(out: Path) -> dict:
    """The sweep record (`CONFIG_FILE`) of a results directory; `SweepError` naming the file
    if it cannot be read."""
    meta_path = Path(out) / CONFIG_FILE
    try:
        meta = json.loads(meta_path.read_text(encoding="utf-8"))
        if not isinstance(meta, dict) or not isinstance(meta.get("canonical"), dict):
            raise ValueError("no 'canonical' table")
    except (OSError, ValueError) as e:
        raise SweepError(f"{meta_path}: unreadable sweep record ({e})") from None
    return meta


def _recorded_change(cfg: SweepConfig, out: Path) -> tuple[dict, str | None]:
    """(the sweep record in `out`, what differs from `cfg`: None if it is this sweep);
    `SweepError` if the record cannot be read."""
    meta = read_record(out)
    if meta.get("fingerprint") == cfg.fingerprint():
        return meta, None
    return meta, _describe_change(meta.get("canonical", {}), cfg.canonical())


def prepare_dir(cfg: SweepConfig, out: Path, resume: bool = False) -> None:
    """Create the results directory or check that it holds this very sweep.

    Raises `SweepError` if it holds a different sweep (naming what changed), holds results of
    something that is not a jaxems sweep, is not empty and no sweep's (`_own_entry`: a
    folder of the user's, whose report.html a sweep wrote over), or (``resume``) has nothing
    to resume. The record
    is written before ``chunks/`` is made, so a run killed in between leaves a directory that
    a rerun continues; an empty ``chunks/`` without a record (such a run of an earlier jaxems)
    holds nothing to mix up and is taken as fresh.
    """
    meta_path = out / CONFIG_FILE
    if meta_path.exists():
        meta, what = _recorded_change(cfg, out)
        if what is not None:
            raise SweepError(
                f"{out} holds the results of a different sweep (changed: {what}; recorded from "
                f"{meta.get('source', '?')}); refusing to mix them. Use another --out directory, "
                f"or delete {out} to start over"
            )
        (out / CHUNK_DIR).mkdir(exist_ok=True)  # a run killed after the record
        return
    if resume:
        raise SweepError(f"{out}: nothing to resume (no {CONFIG_FILE}); run without --resume")
    if finished_chunks(out) or (out / RESULTS_FILE).exists():
        raise SweepError(f"{out}: holds sweep results without {CONFIG_FILE}; refusing to mix "
                         f"them; use another --out directory")
    foreign = sorted(p.name for p in out.iterdir() if not _own_entry(cfg, p)) \
        if out.is_dir() else []
    if foreign:  # a folder of the user's own: its report.html was overwritten
        listed = ", ".join(foreign[:3]) + (", ..." if len(foreign) > 3 else "")
        raise SweepError(f"--out: {out} is not empty and holds no jaxems sweep (no "
                         f"{CONFIG_FILE}; it has {listed}); refusing to write into it: use a "
                         f"new or empty directory")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:  # past `check_out_dir` (root writes where no directory can be made)
        raise SweepError(f"--out: cannot make {out} ({e.strerror or e})") from None
    atomic_write_bytes(out / SOURCE_COPY, cfg.text.encode("utf-8"))
    meta = {"fingerprint": cfg.fingerprint(), "canonical": cfg.canonical(),
            "source": str(cfg.source),
            "created": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
    atomic_write_bytes(meta_path, (json.dumps(meta, indent=1) + "\n").encode("utf-8"))
    (out / CHUNK_DIR).mkdir(exist_ok=True)


def _own_entry(cfg: SweepConfig, p: Path) -> bool:
    """Whether `p`, in a results directory without a record, is what a run of this sweep
    killed before it wrote the record leaves there: its copy of the sweep file (the same
    text), chunks/ (no finished chunk: `prepare_dir` checks), the lock, a temporary file."""
    if p.name == SOURCE_COPY:
        try:
            return p.is_file() and p.read_bytes() == cfg.text.encode("utf-8")
        except OSError:
            return False
    return ((p.name == CHUNK_DIR and p.is_dir()) or p.name == ".lock"
            or (p.name.startswith(".") and ".tmp-" in p.name))


@contextlib.contextmanager
def dir_lock(out: Path):
    """Hold an exclusive lock on a results directory (one sweep process per directory).

    The lock is an `fcntl.flock` on ``DIR/.lock``; the system releases it when the process
    ends, also on ``kill -9``. Without fcntl (Windows) nothing is locked.
    """
    try:
        import fcntl
    except ImportError:  # pragma: no cover
        yield
        return
    fh = open(out / ".lock", "a+")
    try:
        try:
            fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise SweepError(f"{out}: another jaxems sweep is running in this directory") from None
        yield
    finally:
        fh.close()


def finished_chunks(out: Path) -> set[str]:
    """Ids of the chunks with a complete file (temporary files of killed runs are ignored)."""
    d = out / CHUNK_DIR
    if not d.is_dir():
        return set()
    return {p.name[: -len(".parquet")] for p in d.iterdir()
            if p.name.endswith(".parquet") and not p.name.startswith(".")}


def _clean_temporaries(out: Path) -> None:
    for p in (out / CHUNK_DIR).glob(".*.tmp-*"):
        with contextlib.suppress(OSError):
            p.unlink()


def chunk_frame(cfg: SweepConfig, chunk: Chunk, rows: dict[str, Any], points):
    """The rows of one finished chunk as a DataFrame (one row per real grid point)."""
    import pandas as pd

    n = chunk.n_real
    idx = list(chunk.grid_index[:n])
    cols: dict[str, Any] = {
        "route": [cfg.routes[chunk.route_index].name] * n,
        "strategy": [chunk.strategy] * n,
        "grid_index": np.asarray(idx, np.int64),
    }
    for key in grid_columns(cfg):
        cols[key] = np.array([points[i][key] for i in idx], np.float64)
    for f in RESULT_FIELDS:
        cols[f] = rows[f]
    cols["status"] = [str(s) for s in rows["status"]]
    cols["wall_s"] = rows["wall_s"]
    cols["chunk"] = [chunk.id] * n
    return pd.DataFrame(cols)


def grid_columns(cfg: SweepConfig) -> list[str]:
    """Grid value columns of the table: the grid keys, plus mass_kg and battery_MJ always."""
    return list(cfg.grid) + [k for k in ("mass_kg", "battery_MJ") if k not in cfg.grid]


def _full_points(cfg: SweepConfig) -> list[dict[str, float]]:
    """Grid points with the always-present columns filled from the vehicle."""
    fixed = {"mass_kg": float(cfg.vehicle.mass), "battery_MJ": float(cfg.vehicle.E_b_max) / 1e6}
    return [{k: v for k, v in fixed.items() if k not in p} | p for p in cfg.points()]


# --------------------------------------------------------------------------------- results
def add_savings(df):
    """Add fuel_corrected_J and saving_vs_{conventional,baseline}_pct (in place; returned).

    fuel_corrected_J = fuel_J + lambda_b * delta_Eb_J (lambda_b < 0: energy left in the battery
    is worth |lambda_b| J of fuel); 0 correction for strategies without a battery or without a
    finite lambda_b. saving_vs_X_pct = 100 (F_X - F) / F_X with F the corrected fuel of the row
    and F_X that of strategy X on the same route and grid point; NaN where X was not run,
    either row's status is not "ok", or F_X is not positive (nothing to save: a route that X
    runs without fuel, all downhill).
    """
    import pandas as pd

    lam = df["lambda_b"].to_numpy(np.float64)
    dE = df["delta_Eb_J"].to_numpy(np.float64)
    corr = np.where(np.isfinite(lam) & np.isfinite(dE) & ~df["strategy"].isin(NO_BATTERY),
                    lam * dE, 0.0)
    df["fuel_corrected_J"] = df["fuel_J"].to_numpy(np.float64) + corr
    ok = df["status"] == "ok"
    fuel = df["fuel_corrected_J"].where(ok)
    for ref in REFERENCES:
        refs = df.loc[(df["strategy"] == ref) & ok, ["route", "grid_index", "fuel_corrected_J"]]
        refs = refs.rename(columns={"fuel_corrected_J": "_ref"})
        merged = pd.merge(df[["route", "grid_index"]], refs, on=["route", "grid_index"],
                          how="left")
        f_ref = merged["_ref"].to_numpy(np.float64)
        pos = f_ref > 0
        df[f"saving_vs_{ref}_pct"] = np.where(
            pos, 100.0 * (f_ref - fuel.to_numpy(np.float64)) / np.where(pos, f_ref, 1.0), np.nan)
    return df


COMPARE_STRATEGIES = ("conventional", "baseline", "multilevel")


def compare_strategies(route, vehicle="reference_truck", strategies=COMPARE_STRATEGIES, *,
                       dt: float = 1.0, mass_kg: float | None = None,
                       battery_MJ: float | None = None, initial_soc: float | None = None,
                       name: str | None = None, progress: Callable | None = None,
                       on_result: Callable | None = None, **options) -> list[dict]:
    """Several strategies on one route with one vehicle, as a sweep compares them.

    route: a `Route`, a path or a bundled name; vehicle: `VehicleParams` or a name or path;
    mass_kg, battery_MJ, initial_soc: overrides; options: fields of `strategies.Options`, for
    every strategy. Everything is checked before anything compiles (an unknown or repeated
    strategy, a bad option or value: ValueError naming it). on_result(result) (the run's
    `strategies.Result`, its traces included) and then progress(row) are called after each
    run.

    Returns one dict per strategy, in the order given: `Result.as_dict()` plus the sweep's
    fuel_corrected_J and saving_vs_{conventional,baseline}_pct (`add_savings`: positive = less
    fuel than the reference, on corrected fuel; None where the reference was not run or a run
    did not finish), fuel_corrected_l_per_100km, and charge_missed (`report.charge_missed`).
    """
    import pandas as pd

    from .params import with_overrides
    from .report import corrected_l_per_100km
    from .strategies import check_strategy, make_options, named_route, simulate

    if not isinstance(strategies, str | list | tuple):
        raise ValueError(f"strategies: expected a name or a list of names (got "
                         f"{type(strategies).__name__})")
    strategies = [strategies] if isinstance(strategies, str) else list(strategies)
    if not strategies:
        raise ValueError("strategies: none given")
    for s in strategies:
        check_strategy(s)
    if len(set(strategies)) < len(strategies):
        raise ValueError(f"strategies: each at most once (got {', '.join(strategies)})")
    opts = make_options(None, strategies, **options)
    vp = vehicle if isinstance(vehicle, VehicleParams) else load_vehicle(vehicle)
    vp = with_overrides(vp, mass_kg=mass_kg, battery_MJ=battery_MJ, initial_soc=initial_soc)
    name, route = named_route(route, name)  # loaded and checked once
    rows = []
    for s in strategies:
        res = simulate(route, vp, s, dt=dt, options=opts, name=name)
        if on_result is not None:
            on_result(res)
        row = res.as_dict()
        rows.append(row)
        if progress is not None:
            progress(row)
    df = add_savings(pd.DataFrame(rows).assign(grid_index=0,
                                                battery_MJ=float(vp.E_b_max) / 1e6))
    added = {"fuel_corrected_J": df["fuel_corrected_J"].to_numpy(np.float64),
             "fuel_corrected_l_per_100km": corrected_l_per_100km(df),
             **{f"saving_vs_{r}_pct": df[f"saving_vs_{r}_pct"].to_numpy(np.float64)
                for r in REFERENCES}}
    missed = charge_missed(df)
    for i, row in enumerate(rows):
        row |= {k: float(v[i]) if np.isfinite(v[i]) else None for k, v in added.items()}
        row["charge_missed"] = bool(missed[i])
    return rows


def _read_chunk(path: Path):
    """One chunk file; `SweepError` naming it where it cannot be read (chunks are written
    whole, so only something outside jaxems truncates one: deleting it lets --resume compute
    it again)."""
    import pandas as pd

    try:
        return pd.read_parquet(path)
    except Exception as e:  # noqa: BLE001 (pyarrow's errors have no common base but Exception)
        raise SweepError(f"{path}: unreadable chunk file ({type(e).__name__}: {e}); delete it "
                         f"and run the sweep again with --resume to compute it again") from None


def assemble(out: Path, cfg_canonical: dict | None = None):
    """All finished chunk rows of a results directory, ordered, with the savings columns.

    Rows are sorted by (route order, grid_index, strategy order) of the sweep file; chunk files
    of other sweeps are never present (the directory is refused first).
    """
    import pandas as pd

    out = Path(out)
    if cfg_canonical is None:
        cfg_canonical = read_record(out)["canonical"]
    files = sorted((out / CHUNK_DIR).glob("*.parquet"))
    files = [p for p in files if not p.name.startswith(".")]
    if not files:
        raise SweepError(f"{out}: no finished chunks yet")
    df = pd.concat([_read_chunk(p) for p in files], ignore_index=True)
    r_order = {r["name"]: i for i, r in enumerate(cfg_canonical["routes"])}
    s_order = {s: i for i, s in enumerate(cfg_canonical["strategies"])}
    df = df.assign(_r=df["route"].map(r_order), _s=df["strategy"].map(s_order))
    df = df.sort_values(["_r", "grid_index", "_s"], kind="stable").drop(columns=["_r", "_s"])
    df = df.reset_index(drop=True)
    return add_savings(df)


def load_sweep(directory: str | Path):
    """The results of a sweep directory as a pandas DataFrame, one row per (route, grid point,
    strategy).

    Columns: route, strategy, grid_index, the grid values (user units; mass_kg and battery_MJ
    always), the fields of ``jaxems simulate --json`` (length_m, trip_time_s,
    level3_trip_time_s, fuel_J,
    fuel_l_per_100km, delta_Eb_J, Eb_min_J, Eb_max_J, mode_switches, gear_switches, lambda_b,
    max_speed_shortfall_mps, status), level2_status (the last plan's Level 2 flags as an
    integer, `strategies.level2_names`; -1 where the strategy has none), wall_s (wall time per
    configuration), chunk (its chunk id),
    fuel_corrected_J, saving_vs_conventional_pct and saving_vs_baseline_pct (see `add_savings`).
    Reads ``results.parquet`` when it is up to date (no chunk newer, the same chunks: a chunk
    file deleted since was still reported), otherwise merges the finished chunks (an
    unfinished sweep gives the rows computed so far).
    """
    import pandas as pd

    d = Path(directory)
    if not (d / CONFIG_FILE).exists():
        raise SweepError(f"{d}: not a jaxems sweep directory (no {CONFIG_FILE})")
    res = d / RESULTS_FILE
    chunks = [p for p in (d / CHUNK_DIR).glob("*.parquet") if not p.name.startswith(".")]
    if res.exists():
        newest = max((p.stat().st_mtime for p in chunks), default=0.0)
        if res.stat().st_mtime >= newest:
            try:
                df = pd.read_parquet(res)
            except Exception as e:  # noqa: BLE001 (pyarrow's errors, as in `_read_chunk`)
                raise SweepError(f"{res}: not a readable Parquet file ({type(e).__name__}: "
                                 f"{e}); delete it and run the sweep again with --resume, "
                                 f"which merges its chunks into it again") from None
            if set(df["chunk"]) == {p.stem for p in chunks}:
                return df
    return assemble(d)


# ------------------------------------------------------------------------------- execution
@dataclasses.dataclass
class SweepSummary:
    """What a sweep run did (returned by `run_sweep`, printed at the end)."""

    out: Path
    n_configs: int
    n_chunks: int
    computed_chunks: int
    skipped_chunks: int
    computed_configs: int
    wall_s: float
    status_counts: dict[str, int]
    charge_missed: int  # finished runs more than 1 % of their battery off (`report.charge_missed`)
    trip_long: int  # finished runs more than 1 % longer than Level 3's trip (`report.trip_long`)
    chunk_stats: list[dict]  # per computed chunk: id, strategy, route, compiles, wall_s
    results: Path | None
    report: Path | None
    backend: str

    def text(self) -> str:
        """Human-readable summary (a few lines)."""
        rate = self.computed_configs / self.wall_s if self.wall_s > 0 else float("nan")
        st = ", ".join(f"{k} {v}" for k, v in sorted(self.status_counts.items()))
        lines = [
            f"jaxems sweep: {self.n_configs} configurations in {self.n_chunks} chunks "
            f"({self.backend})",
            f"  computed {self.computed_configs} configurations ({self.computed_chunks} chunks) "
            f"in {self.wall_s:.1f} s ({rate:.2f} configurations/s); "
            f"{self.skipped_chunks} chunks already done",
            f"  status: {st or 'no rows'}; {self.charge_missed} end more than "
            f"{100 * CHARGE_SHARE:g} % of their battery from their start, {self.trip_long} "
            f"take more than {100 * TRIP_SHARE:g} % longer than Level 3's trip"
            + (" (listed in the report)" if self.report else ""),
        ]
        if self.results:
            lines.append(f"  results: {self.results}")
        if self.report:
            lines.append(f"  report:  {self.report}")
        return "\n".join(lines)


def default_out(sweep_file: str | Path) -> Path:
    """Default results directory: ``sweeps/<sweep file stem>`` in the current directory."""
    return Path("sweeps") / Path(sweep_file).stem


def _progress(total: int, initial: int, quiet: bool):
    from tqdm import tqdm

    return tqdm(total=total, initial=initial, unit="cfg", desc="sweep", file=sys.stderr,
                disable=quiet, dynamic_ncols=True, smoothing=0.1, mininterval=0.5)


CACHE_ENV = "JAX_COMPILATION_CACHE_DIR"
SCHEDULER_TIMEOUT_S = 30  # how long --scheduler's address is tried before the sweep gives up


def _executor(workers: int | None, scheduler: str | None, cache_dir: Path | None = None):
    """A Dask client (and the cluster it started) or (None, None) for in-process runs.

    Worker processes of a local cluster share JAX's persistent compilation cache in
    `cache_dir` (unless JAX_COMPILATION_CACHE_DIR is set already), so a kernel compiled by one
    worker is loaded, not compiled again, by the others and by later runs.
    """
    if workers is None and scheduler is None:
        return None, None
    from dask.distributed import Client, LocalCluster  # installed: `check_executor`

    if scheduler is not None:
        try:
            return Client(scheduler, timeout=SCHEDULER_TIMEOUT_S), None
        except (OSError, TimeoutError) as e:
            raise SweepError(f"cannot reach the Dask scheduler at {scheduler}: {e}") from None
    env = {}
    if cache_dir is not None and not os.environ.get(CACHE_ENV):
        env[CACHE_ENV] = str(Path(cache_dir).resolve())
    cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                           dashboard_address=None, env=env)
    return Client(cluster), cluster


def check_executor(workers: int | None, scheduler: str | None) -> None:
    """--workers and --scheduler, before anything is written: not both, a whole number >= 1 of
    workers, a Dask address of the scheduler (not yet reached), Dask installed where needed;
    else `SweepError` naming the flag."""
    if workers is not None and scheduler is not None:
        raise SweepError("give either --workers or --scheduler, not both")
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int)
                                or workers < 1):
        raise SweepError(f"--workers: expected a whole number >= 1 (got {workers!r})")
    if workers is None and scheduler is None:
        return
    try:
        from distributed.comm import get_address_host_port
    except ImportError:
        raise SweepError("--workers and --scheduler need Dask distributed: "
                         "pip install 'jaxems[distributed]'") from None
    if scheduler is not None:
        try:
            if not isinstance(scheduler, str) or not scheduler.strip():
                raise ValueError("empty")
            get_address_host_port(scheduler)
        except (ValueError, TypeError) as e:
            raise SweepError(f"--scheduler: {scheduler!r} is not a Dask scheduler address, "
                             f"expected tcp://HOST:PORT ({e})") from None


def check_out_dir(out: Path) -> None:
    """--out before anything is written: a writable directory, or a path that can be made one
    (its nearest existing ancestor a writable directory); else `SweepError` naming --out."""
    from .cli import nearest_existing

    p = nearest_existing(out)
    if not p.is_dir():
        raise SweepError(f"--out: {p} is not a directory" + (f" (in {out})" if p != out else ""))
    if not os.access(p, os.W_OK | os.X_OK):
        raise SweepError(f"--out: the directory {p} is not writable")


def run_sweep(
    sweep_file: str | Path,
    out: str | Path | None = None,
    *,
    workers: int | None = None,
    scheduler: str | None = None,
    resume: bool = False,
    quiet: bool = False,
    report: bool = True,
    client=None,
    on_chunk: Callable[[Chunk], None] | None = None,
) -> SweepSummary:
    """Run (or resume) a sweep; returns a `SweepSummary`. See the module docstring.

    sweep_file: the TOML file (validated completely before any computation); out: results
    directory (default `default_out`); workers: start a local Dask cluster of this many
    processes; scheduler: address of a running Dask scheduler (reached before anything is
    written, where chunks remain: `SweepError` where it cannot be); client: an existing
    `dask.distributed.Client` to use instead; resume: require an existing directory of this
    sweep; quiet: no progress bar; report: write the report at the end; on_chunk: called after
    each chunk file is written (tests).
    """
    check_executor(workers, scheduler)
    if out is not None and not str(out).strip():  # Path("") is the current directory
        raise SweepError(f"--out: expected a directory name (got {str(out)!r})")
    cfg = load_config(sweep_file)
    out = Path(out) if out is not None else default_out(sweep_file)
    check_out_dir(out)
    own_client = None
    if client is None and scheduler is not None and _chunks_left(cfg, out):
        # reached before the directory is made: a scheduler that could not be reached left
        # a skeleton of one (sweep.toml, sweep.json, .lock, chunks/); not for a finished
        # sweep, whose rerun writes its results and report again (it failed with the
        # scheduler gone)
        own_client, _ = _executor(None, scheduler)
    try:
        prepare_dir(cfg, out, resume=resume)
        with dir_lock(out):
            return _run_locked(cfg, out, workers=workers, quiet=quiet, report=report,
                               client=client or own_client, on_chunk=on_chunk,
                               scheduler=scheduler)
    finally:
        if own_client is not None:
            own_client.close()


def _chunks_left(cfg: SweepConfig, out: Path) -> bool:
    """Whether a chunk of `cfg` has no finished file in `out` (whether `out` holds this sweep
    is `prepare_dir`'s to check)."""
    return not {c.id for c in plan_chunks(cfg)} <= finished_chunks(out)


def _run_locked(cfg: SweepConfig, out: Path, *, workers, quiet, report, client,
                on_chunk, scheduler=None) -> SweepSummary:
    """The sweep in its locked directory; client: a Dask client (the caller's, or the
    scheduler's that `run_sweep` reached), or None: where chunks remain, the `scheduler`'s
    (chunks gone since `run_sweep` found none left) or a local cluster of `workers`
    processes, else in-process."""
    _clean_temporaries(out)
    chunks = plan_chunks(cfg)
    points = _full_points(cfg)
    done = finished_chunks(out)
    todo = [c for c in chunks if c.id not in done]
    skipped = len(chunks) - len(todo)
    n_configs = cfg.grid_size * len(cfg.routes) * len(cfg.strategies)
    initial = sum(c.n_real for c in chunks if c.id in done)

    t0 = time.perf_counter()
    stats: list[dict] = []
    own_client = None
    cluster = None
    if client is None and todo:
        own_client, cluster = _executor(workers, scheduler, out / "jax-cache")
        client = own_client
    backend = "in-process" if client is None else (
        f"Dask, {len(client.scheduler_info().get('workers', {}))} workers")
    bar = _progress(n_configs, initial, quiet)
    try:
        steps: dict[int, int] = {}
        for ri in sorted({c.route_index for c in todo}):
            route_chunks = [c for c in chunks if c.route_index == ri]
            steps[ri] = steps_for_route(cfg, cfg.routes[ri].route, route_chunks, points)

        def task_of(c: Chunk) -> ChunkTask:
            vb = vehicle_batch(cfg.vehicle, [points[i] for i in c.grid_index])
            return ChunkTask(chunk=c, vehicles=vb, dt=cfg.dt, n_steps=steps[c.route_index],
                             precision=cfg.precision,
                             options=strategy_options(cfg.options.get(c.strategy)))

        def finish(c: Chunk, rows: dict) -> None:
            df = chunk_frame(cfg, c, rows, points)
            _atomic_write_table(out / CHUNK_DIR / f"{c.id}.parquet", df)
            stats.append({"id": c.id, "route": cfg.routes[c.route_index].name,
                          "strategy": c.strategy, "compiles": int(rows["_compiles"]),
                          "wall_s": float(rows["_wall_s"])})
            bar.update(c.n_real)
            if on_chunk is not None:
                on_chunk(c)

        if client is None:
            for c in todo:
                finish(c, compute_chunk(task_of(c), cfg.routes[c.route_index].route))
        else:
            from dask.distributed import as_completed

            route_futs = {ri: client.scatter(cfg.routes[ri].route, broadcast=False)
                          for ri in steps}
            futs = {}
            token = cfg.fingerprint()[:12]
            first = {}  # one chunk per (route, strategy) first: workers compile different kernels
            for c in todo:
                first.setdefault((c.route_index, c.strategy), c.id)
            for c in todo:
                prio = 1 if first[(c.route_index, c.strategy)] == c.id else 0
                f = client.submit(_compute_remote, task_of(c), route_futs[c.route_index],
                                  key=f"jaxems-{token}-{c.id}", pure=False, priority=prio)
                futs[f] = c
            for f in as_completed(futs):
                finish(futs[f], f.result())
    finally:
        bar.close()
        if own_client is not None:
            own_client.close()
        if cluster is not None:
            import logging

            # the nanny warns when it has to kill a worker that is slow to exit (JAX threads)
            logging.getLogger("distributed.nanny").setLevel(logging.ERROR)
            cluster.close()
    wall = time.perf_counter() - t0

    df = assemble(out, cfg.canonical())
    res_path = out / RESULTS_FILE
    _atomic_write_table(res_path, df)
    report_path = write_report(out, df=df) if report else None
    counts = df["status"].value_counts().to_dict()
    return SweepSummary(
        out=out, n_configs=n_configs, n_chunks=len(chunks), computed_chunks=len(todo),
        skipped_chunks=skipped, computed_configs=sum(c.n_real for c in todo), wall_s=wall,
        status_counts={str(k): int(v) for k, v in counts.items()},
        charge_missed=int(charge_missed(df).sum()), trip_long=int(trip_long(df).sum()),
        chunk_stats=stats,
        results=res_path, report=report_path, backend=backend,
    )


DEMO_SWEEP = Path(__file__).resolve().parent.parent / "examples" / "demo_sweep.toml"


def run_demo(out: str | Path = "out/demo", workers: int | None = 2, quiet: bool = False,
             sweep_file: str | Path = DEMO_SWEEP) -> SweepSummary:
    """The `make demo` sweep (examples/demo_sweep.toml): prints the report path first, runs
    (or resumes) the sweep on a local Dask cluster of `workers` processes (None: in-process),
    writes the report and prints the summary."""
    out = Path(out)
    print(f"jaxems demo sweep: report will be at {out / 'report.html'}", flush=True)
    _set_aside_if_other(load_config(sweep_file), out)
    summary = run_sweep(sweep_file, out, workers=workers, quiet=quiet)
    print(summary.text(), flush=True)
    return summary


def _set_aside_if_other(cfg: SweepConfig, out: Path) -> None:
    """The demo's own directory holding another sweep's results (an earlier jaxems, an edited
    demo file) is moved to ``<out>.stale`` (replacing an older one), so the demo starts over."""
    if not (out / CONFIG_FILE).exists():
        return
    _, what = _recorded_change(cfg, out)
    if what is None:
        return
    stale = out.with_name(out.name + ".stale")
    shutil.rmtree(stale, ignore_errors=True)
    out.rename(stale)
    print(f"jaxems demo sweep: {out} held another sweep's results (changed: {what}); moved "
          f"to {stale}, starting over", flush=True)


# -------------------------------------------------------------------------------------- CLI
def cmd_sweep(args) -> int:
    """`jaxems sweep`: run a fleet sweep (routes x grid x strategies) into a directory."""
    if args.workers is None and args.scheduler is None:
        from .cli import use_compilation_cache

        _in_process_devices(args.devices)
        use_compilation_cache()  # (a local cluster's workers share DIR/jax-cache instead)
    summary = run_sweep(args.sweep_file, args.out, workers=args.workers,
                        scheduler=args.scheduler, resume=args.resume, quiet=args.quiet,
                        report=not args.no_report)
    print(summary.text())
    return 0


def _in_process_devices(n: int | None) -> None:
    """An in-process sweep splits each chunk over `n` CPU devices (default: one per core,
    `shard.use_host_devices`; at most `DEVICES_MAX` or the cores), where JAX has not started
    yet in this process (the command line); otherwise it keeps the devices it has."""
    from . import shard

    cores = os.cpu_count() or 1
    if n is not None and n < 1:
        raise ValueError(f"--devices: must be a whole number >= 1 (got {n})")
    if n is not None and n > max(DEVICES_MAX, cores):
        raise ValueError(f"--devices: at most {max(DEVICES_MAX, cores)} (got {n}; this machine "
                         f"has {cores} cores, and more devices than cores gain nothing)")
    n = n or cores
    if shard.backends_started() is False:
        shard.use_host_devices(n)


def _add_sweep_args(p: argparse.ArgumentParser) -> None:
    from .cli import whole_number

    p.add_argument("sweep_file", metavar="SWEEP.toml", help="the sweep file")
    p.add_argument("--out", metavar="DIR", default=None,
                   help="results directory (default sweeps/<sweep file name>)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--workers", type=whole_number, metavar="N", default=None,
                   help="start a local Dask cluster of N worker processes")
    g.add_argument("--scheduler", metavar="ADDRESS", default=None,
                   help="send chunks to a running Dask scheduler (tcp://HOST:PORT)")
    p.add_argument("--resume", action="store_true",
                   help="continue an interrupted sweep in DIR (a plain rerun does the same)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--no-report", action="store_true", help="do not write report.html")
    p.add_argument("--devices", type=whole_number, metavar="N", default=None,
                   help="in-process: split each chunk over N CPU devices (default: the cores)")
    p.set_defaults(func=cmd_sweep)


def register_sweep(sub) -> None:
    """Add the ``sweep`` subcommand to an argparse subparsers object (`jaxems.cli`)."""
    p = sub.add_parser(
        "sweep", help="fleet sweep: routes x vehicle grid x strategies -> Parquet + report",
        description=cmd_sweep.__doc__ + " The sweep file format is in the README.",
    )
    _add_sweep_args(p)


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m jaxems.sweep SWEEP.toml [...]``: the sweep subcommand on its own."""
    parser = argparse.ArgumentParser(prog="python -m jaxems.sweep", description=cmd_sweep.__doc__)
    _add_sweep_args(parser)
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (RouteError, VehicleError, SweepError, ValueError, OSError) as e:
        print(f"jaxems: error: {' '.join(str(e).split())}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    # run the imported module's main, so that what Dask pickles lives in jaxems.sweep, not __main__
    from jaxems.sweep import main as _main

    sys.exit(_main())
