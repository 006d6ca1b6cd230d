"""Reader of VECTO distance-based driving cycles (`.vdri`).

Format (VECTO user manual, VDRI): comma-separated, header ``<s>,<v>,<grad>,<stop>`` (other VECTO
columns such as ``<Padd>`` are ignored; ``<grad>`` may be missing and then is 0), one row
wherever something changes:

- ``<s>``    travelled distance (m), strictly increasing;
- ``<v>``    target speed (km/h), used as the speed limit vmax(s); 0 marks a stop;
- ``<grad>`` road gradient (%), valid from this row's s to the next row's s;
- ``<stop>`` standstill time (s) of a stop row (v = 0).

A UTF-8 byte-order mark and CRLF line ends are accepted; lines starting with '#' are comments.
"""

from __future__ import annotations

from pathlib import Path

from ..route import DS_DEFAULT, Route, route_from_rows
from ._table import parse_table

COLUMNS = ("<s>", "<v>", "<grad>", "<stop>")


def read_vdri(path: str | Path, ds: float = DS_DEFAULT, bucket: int | None = 512) -> Route:
    """Read a `.vdri` file into a `Route` (grid step `ds` m); errors name file, line, column."""
    rows = parse_table(
        path,
        required={"s_m": "<s>", "v_kmh": "<v>", "stop_s": "<stop>"},
        optional={"grad_pct": ("<grad>", 0.0)},
    )
    return route_from_rows(rows, ds=ds, source=str(path), cols=COLUMNS, bucket=bucket)
