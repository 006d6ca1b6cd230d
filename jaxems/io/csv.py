"""Reader of the jaxems route CSV format (`.csv`).

Comma-separated with a header line; lines starting with '#' are comments; a UTF-8 byte-order
mark and CRLF line ends are accepted. Columns (names exact, case-insensitive, any order, each
once; other columns are ignored; every row has a value for each column of the header, numbers
with a decimal point, not a comma):

=================== ========= ===========================================================
column              unit      meaning
=================== ========= ===========================================================
``distance_m``      m         position along the road, strictly increasing (required)
``speed_limit_km_h`` km/h     speed limit from this row to the next; 0 marks a stop (required)
``gradient_pct``    %         road gradient (rise/run x 100) from this row to the next
                              (optional, default 0; within +-30)
``stop_s``          s         standstill time of a stop row (speed 0) (optional, default 0)
=================== ========= ===========================================================

The rows are sparse like VECTO's: one row wherever something changes, the last row marks the end
of the route. A route that does not begin with a stop is entered at its speed limit.
"""

from __future__ import annotations

from pathlib import Path

from ..route import DS_DEFAULT, Route, route_from_rows
from ._table import parse_table

COLUMNS = ("distance_m", "speed_limit_km_h", "gradient_pct", "stop_s")


def read_csv(path: str | Path, ds: float = DS_DEFAULT, bucket: int | None = 512) -> Route:
    """Read a jaxems route `.csv` into a `Route` (grid step `ds` m); errors name line, column."""
    rows = parse_table(
        path,
        required={"s_m": "distance_m", "v_kmh": "speed_limit_km_h"},
        optional={"grad_pct": ("gradient_pct", 0.0), "stop_s": ("stop_s", 0.0)},
    )
    return route_from_rows(rows, ds=ds, source=str(path), cols=COLUMNS, bucket=bucket)


def write_csv(path: str | Path, rows, comment: str = "") -> None:
    """Write sparse rows (`jaxems.route.Row` or 4-tuples in file units) as a route CSV."""
    with open(path, "w", encoding="utf-8", newline="\n") as fh:
        for line in comment.splitlines():
            fh.write(f"# {line}\n")
        fh.write(",".join(COLUMNS) + "\n")
        for r in rows:
            fh.write(",".join(f"{float(x):g}" for x in tuple(r)[:4]) + "\n")
