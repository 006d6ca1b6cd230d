"""Route file readers: VECTO `.vdri` and the jaxems `.csv` format.

`load_route(path_or_name)` picks the reader from the file suffix; a bare name (no suffix, no
such file) is looked up among the bundled routes in `data/routes/` (e.g. ``short_track`` or
``LongHaul``). `route_name(path)` is the display name (the file stem); names are kept out of the
`Route` pytree.
"""

from __future__ import annotations

from pathlib import Path

from ..params import DATA_DIR
from ..route import BUCKET, DS_DEFAULT, Route, RouteError
from .csv import read_csv, write_csv
from .vecto import read_vdri

ROUTE_DIR = DATA_DIR / "routes"
READERS = {".vdri": read_vdri, ".csv": read_csv}


def list_routes() -> list[Path]:
    """Paths of the bundled routes (`data/routes/**/*.csv|*.vdri`), sorted by name."""
    found = [p for p in ROUTE_DIR.rglob("*") if p.suffix.lower() in READERS and p.is_file()]
    return sorted(found, key=lambda p: (p.suffix.lower() != ".csv", p.stem.lower()))


def resolve_route(path_or_name: str | Path) -> Path:
    """The file for a path, or for the name of a bundled route; `RouteError` if none."""
    p = Path(path_or_name)
    if p.exists() or p.suffix:
        return p
    for q in list_routes():
        if q.stem.lower() == str(path_or_name).lower():
            return q
    known = ", ".join(q.stem for q in list_routes())
    raise RouteError(f"{path_or_name}: no such route file (bundled routes: {known})")


def route_name(path_or_name: str | Path) -> str:
    """Display name of a route file: its stem (``data/routes/short_track.csv`` -> short_track)."""
    return Path(path_or_name).stem


def load_route(
    path_or_name: str | Path, ds: float = DS_DEFAULT, bucket: int | None = BUCKET
) -> Route:
    """Read a route file (`.vdri` or `.csv`) or a bundled route by name into a `Route`.

    ds: requested grid step (m, 1..100); bucket: pad the node count to a multiple of this so
    routes of similar length share compilations (None: no padding). Bad input raises
    `RouteError` (a `ValueError`) naming the file, line and column.
    """
    p = resolve_route(path_or_name)
    if p.is_dir():  # was "unknown route format '.1'" for vecto-3.0.1/
        raise RouteError(f"{p}: is a directory, not a route file")
    reader = READERS.get(p.suffix.lower())
    if reader is None:
        raise RouteError(f"{p}: unknown route format {p.suffix!r} (expected .vdri or .csv)")
    return reader(p, ds=ds, bucket=bucket)


__all__ = [
    "ROUTE_DIR",
    "list_routes",
    "load_route",
    "read_csv",
    "read_vdri",
    "resolve_route",
    "route_name",
    "write_csv",
]
