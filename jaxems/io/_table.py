"""Shared parsing of the sparse route tables (VECTO .vdri and jaxems .csv)."""

from __future__ import annotations

import math
import re
from pathlib import Path

from ..route import RouteError, Row


# a number as the files write it: decimal digits with a point and an exponent, or inf / nan
# (refused as not finite); Python's float() also reads 1_0 as 10 and other scripts' digits
_NUMBER = re.compile(r"[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?|[+-]?(inf|infinity|nan)",
                     re.ASCII | re.IGNORECASE)


def read_lines(path: str | Path) -> list[tuple[int, str]]:
    """(line number, text) of the non-blank, non-comment lines of a UTF-8 text file.

    Accepts a UTF-8 byte-order mark and CRLF or LF line ends; lines starting with '#' are
    comments.
    """
    p = Path(path)
    if not p.exists():
        raise RouteError(f"{path}: no such file")
    if not p.is_file():
        raise RouteError(f"{path}: not a file")
    try:
        text = p.read_bytes().decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise RouteError(f"{path}: not UTF-8 text (byte {e.start})") from None
    except OSError as e:  # "[Errno 5] Input/output error" named no file
        raise RouteError(f"{path}: cannot read ({e.strerror or e})") from None
    out = []
    for i, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if stripped and not stripped.startswith("#"):
            out.append((i, stripped))
    return out


def parse_table(
    path: str | Path,
    required: dict[str, str],
    optional: dict[str, tuple[str, float]],
) -> list[Row]:
    """Parse a comma-separated table with a header line into `Row`s.

    required: field -> header name, for fields among s_m, v_kmh, grad_pct, stop_s.
    optional: field -> (header name, default value).
    Header names match case-insensitively; other columns are ignored. A column read here
    named twice in the header, and a row with more or fewer values than the header has
    columns (a decimal comma: "1,5" for 1.5; empty cells past them, trailing commas, are
    passed over), are `RouteError`s naming the file and line.
    """
    src = str(path)
    lines = read_lines(path)
    if not lines:
        raise RouteError(f"{src}: empty file (no header line)")
    head_no, head = lines[0]
    names = [h.strip().lower() for h in head.split(",")]
    for name in [*required.values(), *(n for n, _ in optional.values())]:
        if names.count(name.lower()) > 1:  # which one holds the values?
            raise RouteError(f"{src}: line {head_no}: column {name} appears "
                             f"{names.count(name.lower())} times (header has: {head})")
    idx: dict[str, int] = {}
    for field, name in required.items():
        if name.lower() not in names:
            raise RouteError(f"{src}: line {head_no}: missing column {name} (header has: {head})")
        idx[field] = names.index(name.lower())
    defaults: dict[str, float] = {}
    for field, (name, default) in optional.items():
        if name.lower() in names:
            idx[field] = names.index(name.lower())
        else:
            defaults[field] = default
    header_of = {f: n for f, n in required.items()} | {f: n for f, (n, _) in optional.items()}
    rows = []
    for no, text in lines[1:]:
        cells = [c.strip() for c in text.split(",")]
        if not any(cells[len(names):]):  # empty cells past the header's (trailing commas)
            cells = cells[:len(names)]
        if len(cells) != len(names):  # more: a decimal comma, or a value without a column
            hint = ("; decimal commas are not read: write 1.5, not 1,5"
                    if len(cells) > len(names) else "")
            raise RouteError(
                f"{src}: line {no}: {len(cells)} values for {len(names)} columns ({text}){hint}"
            )
        vals = dict(defaults)
        for field, k in idx.items():
            cell = cells[k]
            try:
                if not _NUMBER.fullmatch(cell):
                    raise ValueError(cell)
                x = float(cell)
            except ValueError:
                raise RouteError(
                    f"{src}: line {no}, column {header_of[field]}: not a number ({cell!r})"
                ) from None
            if not math.isfinite(x):
                raise RouteError(
                    f"{src}: line {no}, column {header_of[field]}: not a finite number ({cell!r})"
                )
            vals[field] = x
        rows.append(Row(vals["s_m"], vals["v_kmh"], vals["grad_pct"], vals["stop_s"], no))
    return rows
