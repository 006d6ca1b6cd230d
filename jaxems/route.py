"""Routes: a uniform distance grid with road gradient, speed limit and stops.

A `Route` is a `NamedTuple` of arrays only, hence a JAX pytree that `jit` and `vmap` accept.
Names and paths are not leaves: `route_name(path)` gives the display name of a route file.

Grid. Nodes sit at s_i = i * ds, i = 0 .. n-1, with n - 1 = ceil(L / ds_requested) cells, so
that the last node is exactly at the route length L and ds = L / (n - 1) <= ds_requested.
Cell i runs from node i to node i + 1.

Fields (shapes for one route; a batch from `pad_routes` has a leading batch axis):

- ``grade``  (N,)  rise over run of cell i (0.06 = 6 %), the distance-weighted mean of the
  source rows over the cell (so the elevation at every node is exact); 0 on the last node and
  on padding.
- ``vmax``   (N,)  speed limit at node i (m/s): the smallest limit the source gives anywhere in
  the two cells next to the node, so that the limit holds everywhere between nodes.
- ``stop``   (N,)  standstill time at node i (s); > 0 marks a stop. A stop in the source is
  moved to the nearest node (durations of stops that land on the same node add up).
- ``mask``   (N,)  True for the n valid nodes; padding nodes (False) follow them.
- ``ds``     ()    cell length (m).
- ``length`` ()    route length L (m) = (n - 1) * ds.

Start and end. A route whose first node is a stop starts from standstill; otherwise it is
entered at its speed limit (a "flying start", like a lap of a test track). A route whose last
node is a stop ends at standstill; otherwise the end is free.

Sparse rows. Both file formats (`jaxems.io`) list rows (s, v, grad, stop) wherever something
changes; each row's speed v and gradient hold from its s to the next row's s, the last row marks
the end of the route. A row with v = 0 is a stop of `stop` seconds at its s, and over the stretch
up to the next row the limit is the next moving row's speed (the vehicle pulls away towards it).
`route_from_rows` turns rows into a `Route` and checks them; the readers check each value first
so that errors name the file, line and column.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np

KMH = 1.0 / 3.6  # m/s per km/h

DS_DEFAULT = 10.0  # m, default cell length
DS_RANGE = (1.0, 100.0)  # m, accepted requested cell lengths
BUCKET = 512  # nodes: routes are padded to a multiple of this so batches share compiles
SPEED_MAX_KMH = 200.0  # highest accepted speed limit
SPEED_MIN_KMH = 1.8  # lowest accepted non-zero speed limit: Level 3's crawl floor (0.5 m/s)
GRADE_MAX_PCT = 30.0  # steepest accepted gradient (either sign)
STOP_MAX_S = 86400.0  # longest accepted standstill (a day)
LENGTH_RANGE_M = (1.0, 5.0e6)  # accepted route lengths: the smallest cell to 5000 km


class RouteError(ValueError):
    """A route file or route data is wrong; the message names the file, line and column."""


class Route(NamedTuple):
    """One route on a uniform distance grid (all leaves are arrays; see the module docstring).

    grade: (N,) rise/run per cell; vmax: (N,) m/s per node; stop: (N,) s per node;
    mask: (N,) bool; ds: () m; length: () m.
    """

    grade: Any
    vmax: Any
    stop: Any
    mask: Any
    ds: Any
    length: Any


class Row(NamedTuple):
    """One source row, in file units, with its line number for error messages."""

    s_m: float
    v_kmh: float
    grad_pct: float
    stop_s: float
    line: int = 0


def _where(source: str, line: int, col: str) -> str:
    return f"{source}: line {line}, column {col}" if line else f"{source}: row, column {col}"


def check_rows(rows: Sequence[Row], source: str, cols: tuple[str, str, str, str]) -> None:
    """Validate source rows; `cols` are the file's names of (s, v, grad, stop) for messages.

    Raises `RouteError` naming file, line and column for: too few rows, distance not
    increasing or starting below 0, a length outside LENGTH_RANGE_M, negative speed, speed
    above 200 km/h or in (0, 1.8) km/h, gradient beyond +-30 %, negative stop time or one
    above a day, a stop row (v = 0) with no duration, a stop time on a moving row, no moving
    row.
    """
    c_s, c_v, c_g, c_stop = cols
    if len(rows) == 0:
        raise RouteError(f"{source}: empty file (no data rows)")
    if len(rows) < 2:
        raise RouteError(
            f"{source}: line {rows[0].line}: only one data row; a route needs a start row and "
            f"an end row"
        )
    for r in rows:
        for name, val in zip(cols, (r.s_m, r.v_kmh, r.grad_pct, r.stop_s), strict=True):
            if not math.isfinite(val):
                raise RouteError(f"{_where(source, r.line, name)}: not a finite number ({val})")
        if r.v_kmh < 0:
            raise RouteError(f"{_where(source, r.line, c_v)}: negative speed ({r.v_kmh:g} km/h)")
        if r.v_kmh > SPEED_MAX_KMH:
            raise RouteError(
                f"{_where(source, r.line, c_v)}: speed {r.v_kmh:g} km/h above "
                f"{SPEED_MAX_KMH:g} km/h"
            )
        if 0 < r.v_kmh < SPEED_MIN_KMH:
            raise RouteError(
                f"{_where(source, r.line, c_v)}: speed {r.v_kmh:g} km/h below "
                f"{SPEED_MIN_KMH:g} km/h, the slowest the prediction drives (0 marks a stop)"
            )
        if abs(r.grad_pct) > GRADE_MAX_PCT:
            raise RouteError(
                f"{_where(source, r.line, c_g)}: gradient {r.grad_pct:g} % beyond "
                f"+-{GRADE_MAX_PCT:g} %"
            )
        if r.stop_s < 0:
            raise RouteError(
                f"{_where(source, r.line, c_stop)}: negative stop time ({r.stop_s:g} s)"
            )
        if r.stop_s > STOP_MAX_S:
            raise RouteError(
                f"{_where(source, r.line, c_stop)}: stop time {r.stop_s:g} s above "
                f"{STOP_MAX_S:g} s (a day)"
            )
        if r.v_kmh == 0 and r.stop_s == 0:
            raise RouteError(
                f"{_where(source, r.line, c_stop)}: a stop (speed 0) with no duration; give the "
                f"standstill time in seconds"
            )
        if r.v_kmh > 0 and r.stop_s > 0:
            raise RouteError(
                f"{_where(source, r.line, c_stop)}: stop time {r.stop_s:g} s on a row with speed "
                f"{r.v_kmh:g} km/h; a stop row has speed 0"
            )
    if rows[0].s_m < 0:  # -100 was taken as the route's start
        raise RouteError(f"{_where(source, rows[0].line, c_s)}: the distance starts at "
                         f"{rows[0].s_m:g} m; distances are >= 0 (the distance travelled)")
    for prev, r in zip(rows[:-1], rows[1:], strict=True):
        if not r.s_m > prev.s_m:
            raise RouteError(
                f"{_where(source, r.line, c_s)}: distance not increasing ({r.s_m:g} m after "
                f"{prev.s_m:g} m on line {prev.line})"
            )
    if all(r.v_kmh == 0 for r in rows):
        raise RouteError(f"{source}: no row with a non-zero speed; the route never moves")
    length = rows[-1].s_m - rows[0].s_m
    if not LENGTH_RANGE_M[0] <= length <= LENGTH_RANGE_M[1]:
        raise RouteError(
            f"{_where(source, rows[-1].line, c_s)}: route length {length:g} m outside "
            f"{LENGTH_RANGE_M[0]:g} m to {LENGTH_RANGE_M[1] / 1e3:g} km"
        )


def _first(bad) -> tuple:
    """The index (a tuple; () for a scalar) of the first True of the bool array `bad`."""
    return tuple(int(i) for i in np.argwhere(bad)[0])


def _index_text(at: tuple) -> str:
    """The text `[i, j]` of an index (empty for a scalar's): where in a batch or a route an
    error lies."""
    return f"[{', '.join(str(i) for i in at)}]" if at else ""


def _route_leaves(route: Route) -> dict | None:
    """The leaves of `route` as float64 arrays (the mask as it is), None where one is traced
    (under `jit`); a leaf that is not numbers is a `RouteError` naming it."""
    import jax  # (here: the readers need no JAX)

    if not isinstance(route, Route):
        raise RouteError(f"route: expected a Route (got {type(route).__name__})")
    if any(isinstance(getattr(route, k), jax.core.Tracer) for k in Route._fields):
        return None
    leaves = {}
    for k in Route._fields:
        x = getattr(route, k)
        if x is None or isinstance(x, str | bytes):
            raise RouteError(f"route {k}: must be an array of numbers (got {type(x).__name__})")
        try:
            a = np.asarray(x)
            leaves[k] = a if k == "mask" else a.astype(np.float64)
        except (TypeError, ValueError) as e:
            raise RouteError(f"route {k}: must be an array of numbers (got {type(x).__name__}: "
                             f"{e})") from None
        if leaves[k].dtype == object:
            raise RouteError(f"route {k}: must be an array of numbers (got {type(x).__name__})")
    return leaves


def _check_route_shapes(leaves: dict) -> None:
    """The leaves fit together (see the module docstring): grade, vmax, stop and mask (..., N)
    alike with N >= 2, ds and length of shape (...), and a boolean mask that keeps a prefix of
    at least 2 nodes (the padding follows them); else a `RouteError`."""
    shape = leaves["grade"].shape
    if len(shape) < 1 or shape[-1] < 2:
        raise RouteError(f"route grade: must be an array of at least 2 nodes (got shape {shape})")
    for k in ("vmax", "stop", "mask"):
        if leaves[k].shape != shape:
            raise RouteError(f"route {k}: must have grade's shape {shape} (got {leaves[k].shape})")
    for k in ("ds", "length"):
        if leaves[k].shape != shape[:-1]:
            raise RouteError(f"route {k}: must have shape {shape[:-1]} (one a route; got "
                             f"{leaves[k].shape})")
    mask = leaves["mask"]
    if mask.dtype != np.bool_:
        raise RouteError(f"route mask: must be booleans (got dtype {mask.dtype})")
    n = mask.sum(axis=-1)
    prefix = np.arange(shape[-1]) < n[..., None]
    for bad, why in ((n < 2, "must keep at least 2 nodes"),
                     (np.any(mask != prefix, axis=-1), "must keep the first nodes (the padding, "
                      "False, follows them)")):
        if np.any(bad):
            at = _first(bad)
            raise RouteError(f"route mask{_index_text(at)}: {why} (it keeps {int(n[at])} of "
                             f"{shape[-1]})")


def _check_route_length(leaves: dict) -> None:
    """length = (n - 1) ds, n the kept nodes (ds and length checked on their own first)."""
    want = (leaves["mask"].sum(axis=-1) - 1) * leaves["ds"]
    with np.errstate(invalid="ignore"):
        bad = ~(np.abs(leaves["length"] - want) <= 1e-6 * np.maximum(np.abs(want), 1.0))
    if np.any(bad):
        at = _first(bad)
        raise RouteError(f"route length{_index_text(at)}: must be (kept nodes - 1) * ds = "
                         f"{float(want[at]):.6g} m (got {float(leaves['length'][at])!r})")


def check_route(route: Route) -> Route:
    """`route` where its arrays are what a route file gives (for routes built or changed in
    Python; files are checked as they load): arrays of numbers whose shapes fit together
    (`_check_route_shapes`: a kept prefix of at least 2 nodes), length = (n - 1) ds, ds finite
    and > 0, length in LENGTH_RANGE_M, and on every node the mask keeps a finite gradient
    within +-GRADE_MAX_PCT, a speed limit in [SPEED_MIN_KMH, SPEED_MAX_KMH] and a standstill
    time in [0, STOP_MAX_S]; else a `RouteError` naming the field and the node (in a batch,
    [route, node]). Traced leaves (under `jit`) are left to a concrete call. Returns the route
    with every leaf an array (a list or a number made a NumPy array)."""
    leaves = _route_leaves(route)
    if leaves is None:
        return route
    if not all(hasattr(x, "dtype") for x in route):
        route = Route(*(x if hasattr(x, "dtype") else np.asarray(x) for x in route))
    keep = leaves["mask"]
    rules = {
        "ds": (lambda x: np.isfinite(x) & (x > 0), "must be a finite distance > 0 m", True),
        "length": (lambda x: (x >= LENGTH_RANGE_M[0]) & (x <= LENGTH_RANGE_M[1]),
                   f"must be a distance from {LENGTH_RANGE_M[0]:g} to {LENGTH_RANGE_M[1]:g} m",
                   True),
        "grade": (lambda x: np.isfinite(x) & (np.abs(x) <= GRADE_MAX_PCT / 100),
                  f"must be a finite rise/run within +-{GRADE_MAX_PCT / 100:g}", keep),
        "vmax": (lambda x: (x >= SPEED_MIN_KMH * KMH * (1 - 1e-9)) & (x <= SPEED_MAX_KMH * KMH),
                 f"must be a speed limit in [{SPEED_MIN_KMH / 3.6:.4g}, "
                 f"{SPEED_MAX_KMH / 3.6:.4g}] m/s", keep),
        "stop": (lambda x: (x >= 0) & (x <= STOP_MAX_S),
                 f"must be a standstill time from 0 to {STOP_MAX_S:g} s", keep),
    }
    _check_route_shapes(leaves)
    for field, (ok, why, where) in rules.items():
        x = leaves[field]
        with np.errstate(invalid="ignore"):
            bad = np.broadcast_to(where, x.shape) & ~ok(x)
        if np.any(bad):
            at = _first(bad)
            raise RouteError(f"route {field}{_index_text(at)}: {why} (got {float(x[at])!r})")
    _check_route_length(leaves)
    return route


def route_from_rows(
    rows: Sequence[Row],
    ds: float = DS_DEFAULT,
    source: str = "<rows>",
    cols: tuple[str, str, str, str] = ("s", "v", "grad", "stop"),
    bucket: int | None = BUCKET,
) -> Route:
    """Build a `Route` from sparse rows (file units: m, km/h, %, s); see the module docstring.

    ds: requested cell length (m), 1..100; the grid uses L / ceil(L / ds).
    bucket: pad the node count up to a multiple of this (None: no padding).
    """
    if not (isinstance(ds, numbers.Real) and not isinstance(ds, bool)
            and DS_RANGE[0] <= ds <= DS_RANGE[1]):
        raise RouteError(
            f"{source}: ds must be a number from {DS_RANGE[0]:g} to {DS_RANGE[1]:g} m (got {ds!r})"
        )
    ds = float(ds)
    check_rows(rows, source, cols)
    s_rows = np.array([r.s_m for r in rows], dtype=np.float64)
    s_rows = s_rows - s_rows[0]
    v_rows = np.array([r.v_kmh for r in rows], dtype=np.float64) * KMH
    g_rows = np.array([r.grad_pct for r in rows], dtype=np.float64) / 100.0
    stop_rows = np.array([r.stop_s for r in rows], dtype=np.float64)
    L = float(s_rows[-1])
    n_cells = max(1, math.ceil(L / ds - 1e-9))
    ds_eff = L / n_cells
    n = n_cells + 1
    s_nodes = np.arange(n) * ds_eff
    s_nodes[-1] = L

    # segments j = 0 .. R-2: [s_j, s_{j+1}) with grade g_j and limit lim_j
    seg_lim = v_rows[:-1].copy()
    moving = v_rows > 0
    nxt = None
    for j in range(len(rows) - 2, -1, -1):  # stop rows: the next moving row's speed
        if moving[j + 1]:
            nxt = v_rows[j + 1]
        if not moving[j]:
            seg_lim[j] = nxt if nxt is not None else np.nan
    if np.any(np.isnan(seg_lim)):  # stops with only stops after them: the previous limit
        last = np.nan
        for j in range(len(seg_lim)):
            last = seg_lim[j] if not np.isnan(seg_lim[j]) else last
            seg_lim[j] = last
    # grade: exact cell means from the cumulative rise
    rise = np.concatenate([[0.0], np.cumsum(g_rows[:-1] * np.diff(s_rows))])
    rise_nodes = np.interp(s_nodes, s_rows, rise)
    grade = np.zeros(n)
    grade[:-1] = np.diff(rise_nodes) / ds_eff
    # a cell's mean lies within its rows' gradients, which are within the limit: rounding may
    # not take it past (a 30 % row gave cells of 0.30000000000000016, which `check_route`
    # then refused)
    grade = np.clip(grade, -GRADE_MAX_PCT / 100.0, GRADE_MAX_PCT / 100.0)
    # speed limit per cell: the smallest limit of any segment that overlaps the open cell
    starts = s_rows[:-1]
    lo = np.searchsorted(starts, s_nodes[:-1], side="right") - 1
    hi = np.searchsorted(starts, s_nodes[1:], side="left") - 1
    cell_lim = np.array([seg_lim[a : max(a, b) + 1].min() for a, b in zip(lo, hi, strict=True)])
    vmax = np.empty(n)
    vmax[0] = cell_lim[0]
    vmax[-1] = cell_lim[-1]
    vmax[1:-1] = np.minimum(cell_lim[:-1], cell_lim[1:])
    stop = np.zeros(n)
    for j in np.flatnonzero(stop_rows > 0):
        stop[int(np.clip(np.rint(s_rows[j] / ds_eff), 0, n - 1))] += stop_rows[j]
    route = Route(
        grade=grade,
        vmax=vmax,
        stop=stop,
        mask=np.ones(n, dtype=bool),
        ds=np.float64(ds_eff),
        length=np.float64(L),
    )
    if bucket:
        route = pad_route(route, _round_up(n, bucket))
    return route


def _round_up(n: int, bucket: int) -> int:
    return int(math.ceil(n / bucket) * bucket)


def n_nodes(route: Route) -> int:
    """Number of valid nodes of one route (host-side)."""
    return int(np.sum(np.asarray(route.mask)))


def pad_route(route: Route, n: int) -> Route:
    """Pad one route to n nodes (mask False, grade 0, stop 0, vmax of the last valid node)."""
    route = Route(*(np.asarray(x) for x in route))
    N = route.grade.shape[-1]
    if route.grade.ndim != 1:
        raise RouteError("pad_route: expected one route (1-D arrays)")
    if n < N:
        if np.any(route.mask[n:]):
            raise RouteError(f"pad_route: cannot pad a route of {n_nodes(route)} nodes to {n}")
        return Route(*(x[:n] if x.ndim else x for x in route))
    k = n - N
    last = route.vmax[route.mask][-1]
    return Route(
        grade=np.concatenate([route.grade, np.zeros(k)]),
        vmax=np.concatenate([route.vmax, np.full(k, last)]),
        stop=np.concatenate([route.stop, np.zeros(k)]),
        mask=np.concatenate([route.mask, np.zeros(k, dtype=bool)]),
        ds=route.ds,
        length=route.length,
    )


def pad_routes(routes: Sequence[Route], bucket: int = BUCKET) -> Route:
    """Stack routes of different lengths into one batch: leaves get a leading axis (B, ...).

    Every route is padded to the same node count, the longest one rounded up to a multiple of
    `bucket`, so batches of similar routes share one compilation.
    """
    if not routes:
        raise RouteError("pad_routes: empty list of routes")
    n = _round_up(max(n_nodes(r) for r in routes), bucket)
    padded = [pad_route(r, n) for r in routes]
    return Route(*(np.stack(leaves) for leaves in zip(*padded, strict=True)))


def unstack_routes(batch: Route) -> list[Route]:
    """The routes of a batch made by `pad_routes` (each keeps the batch's padding)."""
    b = np.shape(batch.ds)[0]
    return [Route(*(np.asarray(x)[i] for x in batch)) for i in range(b)]


def node_positions(route: Route):
    """s (N,) (m): node positions i * ds (padding nodes continue the grid)."""
    N = np.shape(route.grade)[-1]
    s = np.arange(N) * np.asarray(route.ds, dtype=np.float64)[..., None]
    return s


def elevation(route: Route):
    """Elevation (N,) (m) relative to the start, from the cell grades (rise = ds sin(atan g)).

    The distance s is measured along the road, so a cell of length ds rises ds sin(alpha).
    """
    g = np.asarray(route.grade)
    rise = np.asarray(route.ds)[..., None] * np.sin(np.arctan(g)) * np.asarray(route.mask)
    h = np.concatenate([np.zeros(g.shape[:-1] + (1,)), np.cumsum(rise[..., :-1], axis=-1)], -1)
    return h


def route_summary(route: Route) -> dict:
    """Host-side facts of one route: length, gradient range, speed-limit range, stops."""
    m = np.asarray(route.mask)
    n = int(m.sum())
    g = np.asarray(route.grade)[: n - 1] * 100.0
    vmax = np.asarray(route.vmax)[:n] / KMH
    stop = np.asarray(route.stop)[:n]
    return {
        "length_m": float(route.length),
        "nodes": n,
        "ds_m": float(route.ds),
        "gradient_min_pct": float(g.min()),
        "gradient_max_pct": float(g.max()),
        "speed_limit_min_km_h": float(vmax.min()),
        "speed_limit_max_km_h": float(vmax.max()),
        "stops": int(np.count_nonzero(stop > 0)),
        "stop_time_s": float(stop.sum()),
        "starts_stopped": bool(stop[0] > 0),
        "ends_stopped": bool(stop[n - 1] > 0),
    }
