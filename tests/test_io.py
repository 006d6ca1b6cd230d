"""Route readers: bundled data, BOM/CRLF, and one clear error per kind of bad input."""

import numpy as np
import pytest

from jaxems.io import ROUTE_DIR, list_routes, load_route, read_csv, read_vdri, route_name
from jaxems.io.csv import write_csv
from jaxems.route import RouteError, Row, elevation, n_nodes, route_summary

VECTO = ROUTE_DIR / "vecto-3.0.1"
VDRI_TEXT = (
    "<s>,<v>,<grad>,<stop>\n0,0,1.5,3\n10,40,1.5,0\n250,60,-2,0\n400,0,-2,12\n"
    "410,50,0,0\n900,50,0,0\n"
)
CSV_TEXT = (
    "# a comment\ndistance_m,speed_limit_km_h,gradient_pct,stop_s\n0,0,1.5,3\n10,40,1.5,0\n"
    "250,60,-2,0\n400,0,-2,12\n410,50,0,0\n900,50,0,0\n"
)


def _same(a, b):
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


# ------------------------------------------------------------------------------ bundled data
@pytest.mark.parametrize(
    "name,km,gmin,gmax,stops,stop_s",
    [
        ("LongHaul", 108.2, -6.96, 6.73, 6, 244),
        ("RegionalDelivery", 25.8, -5.26, 5.59, 6, 114),
        ("UrbanDelivery", 27.8, -7.56, 6.11, 27, 639),
    ],
)
def test_bundled_vecto_cycles_match_their_attribution(name, km, gmin, gmax, stops, stop_s):
    r = load_route(VECTO / f"{name}.vdri")
    info = route_summary(r)
    assert info["length_m"] / 1000 == pytest.approx(km, abs=0.05)
    # cell means can only narrow the range of the source rows
    assert gmin - 0.01 <= info["gradient_min_pct"] and info["gradient_max_pct"] <= gmax + 0.01
    # and they keep its climbs: the rise over every cell is the source's, read as plain CSV
    # (<s>,<v>,<grad>,<stop>; a row's gradient holds up to the next row)
    rows = np.array([[float(x) for x in line.split(",")] for line in
                     (VECTO / f"{name}.vdri").read_text().splitlines()[1:] if line.strip()])
    rise_rows = np.concatenate([[0.0], np.cumsum(rows[:-1, 2] / 100 * np.diff(rows[:, 0]))])
    n = n_nodes(r)
    s_nodes = np.minimum(np.arange(n) * float(r.ds), float(r.length))
    rise = np.concatenate([[0.0], np.cumsum(np.asarray(r.grade)[: n - 1] * np.diff(s_nodes))])
    np.testing.assert_allclose(rise, np.interp(s_nodes, rows[:, 0], rise_rows), rtol=0,
                               atol=1e-6)
    assert np.ptp(rise) > 20.0  # (hills of 50-340 m: the check is not of a flat route)
    assert info["stops"] == stops and info["stop_time_s"] == stop_s
    assert info["starts_stopped"] and info["ends_stopped"]
    assert (VECTO / "LICENSE.txt").is_file() and "EUPL" in (VECTO / "LICENSE.txt").read_text()
    assert "vecto" in (VECTO / "SOURCES.md").read_text().lower()


def test_short_track_reconstruction():
    r = load_route("short_track")
    info = route_summary(r)
    assert info["length_m"] == 1055.0
    assert info["stops"] == 0 and not info["starts_stopped"]
    assert info["speed_limit_min_km_h"] == info["speed_limit_max_km_h"] == 25.0
    r5 = load_route("short_track", ds=5.0, bucket=None)  # every row on a node
    g = np.round(r5.grade[: n_nodes(r5) - 1] * 100, 9)
    runs = [g[0]] + [b for a, b in zip(g[:-1], g[1:], strict=True) if b != a]
    assert runs == [0, 6, 0, -12, 0, 12, 0, -6, 0]
    h = elevation(r5)
    assert h[n_nodes(r5) - 1] == pytest.approx(0.0, abs=1e-9)  # a closed track
    assert h.max() == pytest.approx(150 * np.sin(np.arctan(0.06)), rel=1e-9)


def test_list_and_names():
    names = [route_name(p) for p in list_routes()]
    assert names[0] == "short_track"
    assert {"LongHaul", "RegionalDelivery", "UrbanDelivery"} <= set(names)
    assert route_name("a/b/Foo.vdri") == "Foo"
    _same(load_route("longhaul"), load_route(VECTO / "LongHaul.vdri"))


# ----------------------------------------------------------------------------- formats
def test_vdri_and_csv_agree(tmp_path):
    (tmp_path / "a.vdri").write_text(VDRI_TEXT)
    (tmp_path / "a.csv").write_text(CSV_TEXT)
    a, b = read_vdri(tmp_path / "a.vdri"), read_csv(tmp_path / "a.csv")
    _same(a, b)
    info = route_summary(a)
    assert info["stops"] == 2 and info["stop_time_s"] == 15 and info["length_m"] == 900


@pytest.mark.parametrize("suffix,text", [(".vdri", VDRI_TEXT), (".csv", CSV_TEXT)])
def test_bom_and_crlf(tmp_path, suffix, text):
    plain = tmp_path / f"plain{suffix}"
    plain.write_text(text)
    odd = tmp_path / f"odd{suffix}"
    odd.write_bytes(b"\xef\xbb\xbf" + text.replace("\n", "\r\n").encode())
    assert odd.read_bytes()[:3] == b"\xef\xbb\xbf" and b"\r\n" in odd.read_bytes()
    _same(load_route(plain), load_route(odd))


def test_optional_columns_extra_columns_and_order(tmp_path):
    p = tmp_path / "x.csv"
    p.write_text("Speed_Limit_km_h, note ,distance_m\n50,a,0\n50,b,300\n")
    r = load_route(p)
    assert float(r.length) == 300 and not r.stop.any() and not r.grade.any()
    q = tmp_path / "x.vdri"
    q.write_text("<s>,<v>,<stop>,<Padd>\n0,50,0,1.0\n300,50,0,1.0\n")
    _same(r, load_route(q))


def test_write_csv_round_trip(tmp_path):
    rows = [Row(0, 0, 2, 5), Row(100, 30, -3, 0), Row(500, 30, 0, 0)]
    p = tmp_path / "w.csv"
    write_csv(p, rows, comment="made by a test")
    assert p.read_text().startswith("# made by a test\n")
    r = load_route(p)
    assert float(r.length) == 500 and r.stop[0] == 5


# ----------------------------------------------------------------------------- bad input
BAD = [
    # (name, text, line, column, words)
    ("empty", "", None, None, "empty file"),
    ("blank", "\n\n", None, None, "empty file"),
    ("header only", "<s>,<v>,<grad>,<stop>\n", None, None, "empty file"),
    ("one row", "<s>,<v>,<grad>,<stop>\n0,50,0,0\n", 2, None, "only one data row"),
    ("missing column", "<s>,<grad>,<stop>\n0,0,0\n100,0,0\n", 1, "<v>", "missing column"),
    ("nan", "<s>,<v>,<grad>,<stop>\n0,50,nan,0\n100,50,0,0\n", 2, "<grad>", "finite"),
    ("inf", "<s>,<v>,<grad>,<stop>\n0,50,0,0\n100,inf,0,0\n", 3, "<v>", "finite"),
    ("text", "<s>,<v>,<grad>,<stop>\n0,50,0,0\n100,fast,0,0\n", 3, "<v>", "not a number"),
    ("empty cell", "<s>,<v>,<grad>,<stop>\n0,50,,0\n100,50,0,0\n", 2, "<grad>", "not a number"),
    ("short row", "<s>,<v>,<grad>,<stop>\n0,50,0,0\n100,50\n", 3, None, "3 values|2 values"),
    ("same distance", "<s>,<v>,<grad>,<stop>\n0,50,0,0\n0,50,0,0\n", 3, "<s>", "not increasing"),
    (
        "going back",
        "<s>,<v>,<grad>,<stop>\n0,50,0,0\n90,50,0,0\n80,50,0,0\n",
        4,
        "<s>",
        "not increasing",
    ),
    ("negative speed", "<s>,<v>,<grad>,<stop>\n0,-1,0,0\n100,50,0,0\n", 2, "<v>", "negative"),
    ("too fast", "<s>,<v>,<grad>,<stop>\n0,50,0,0\n100,250,0,0\n", 3, "<v>", "above 200"),
    ("steep", "<s>,<v>,<grad>,<stop>\n0,50,35,0\n100,50,0,0\n", 2, "<grad>", "beyond"),
    ("steep down", "<s>,<v>,<grad>,<stop>\n0,50,0,0\n100,50,-30.01,0\n", 3, "<grad>", "beyond"),
    (
        "stop no duration",
        "<s>,<v>,<grad>,<stop>\n0,50,0,0\n50,0,0,0\n100,50,0,0\n",
        3,
        "<stop>",
        "no duration",
    ),
    ("negative stop", "<s>,<v>,<grad>,<stop>\n0,0,0,-3\n100,50,0,0\n", 2, "<stop>", "negative"),
    # a value beyond the header's columns was dropped; a column named twice read the first
    ("long row", "<s>,<v>,<grad>,<stop>\n0,50,0,0,7\n100,50,0,0\n", 2, None, "5 values for 4"),
    ("column twice", "<s>,<v>,<grad>,<v>\n0,50,0,0\n100,50,0,0\n", 1, "<v>", "appears 2 times"),
    ("underscore", "<s>,<v>,<grad>,<stop>\n0,50,0,0\n1_00,50,0,0\n", 3, "<s>",
     r"not a number \('1_00'\)"),
]


@pytest.mark.parametrize("name,text,line,col,words", BAD, ids=[b[0] for b in BAD])
def test_bad_vdri(tmp_path, name, text, line, col, words):
    p = tmp_path / "bad.vdri"
    p.write_text(text)
    with pytest.raises(RouteError, match=words) as e:
        load_route(p)
    msg = str(e.value)
    assert msg.startswith(str(p)), msg
    if line is not None:
        assert f"line {line}" in msg, msg
    if col is not None:
        assert f"column {col}" in msg, msg
    assert "\n" not in msg


CSV_HEAD = "distance_m,speed_limit_km_h,gradient_pct,stop_s\n"


@pytest.mark.parametrize(
    "body,line,col,words",
    [
        ("", None, None, "empty file"),
        ("0,50,0,0\n100,50,x,0\n", 3, "gradient_pct", "not a number"),
        ("0,50,0,0\n100,NaN,0,0\n", 3, "speed_limit_km_h", "finite"),
        ("0,50,0,0\n50,0,0,0\n100,50,0,0\n", 3, "stop_s", "no duration"),
        ("0,50,0,0\n-10,50,0,0\n", 3, "distance_m", "not increasing"),
        ("0,201,0,0\n100,50,0,0\n", 2, "speed_limit_km_h", "above 200"),
        ("0,50,31,0\n100,50,0,0\n", 2, "gradient_pct", "beyond"),
        # values that ran out of memory, overflowed deep in JAX or were silently floored
        ("0,0,0,1e20\n100,25,0,0\n", 2, "stop_s", "above 86400 s"),
        ("0,25,0,0\n1e9,25,0,0\n", 3, "distance_m", "route length 1e\\+09 m outside"),
        ("0,0.001,0,0\n100,0.001,0,0\n", 2, "speed_limit_km_h", "below 1.8 km/h"),
        ("0,25,0,0\n0.001,25,0,0\n", 3, "distance_m", "outside 1 m"),
        # a decimal comma: 1,5 % was read as 1 % with the 5 dropped
        ("0,25,1,5,0\n100,25,0,0\n", 2, None, "5 values for 4 columns .*decimal comma"),
        # Python's float() reads 1_0 as 10 and Arabic-Indic digits as digits
        ("0,25,0,0\n500,25,1_0,0\n", 3, "gradient_pct", r"not a number \('1_0'\)"),
        ("0,25,0,0\n\u0665\u0660\u0660,25,0,0\n", 3, "distance_m", "not a number"),
        ("0,25,0,0\n500,25,inf,0\n", 3, "gradient_pct", r"not a finite number \('inf'\)"),
        # a route starting at -100 m was taken
        ("-100,25,0,0\n500,25,0,0\n", 2, "distance_m", "the distance starts at -100 m"),
    ],
)
def test_bad_csv(tmp_path, body, line, col, words):
    p = tmp_path / "bad.csv"
    p.write_text(CSV_HEAD + body)
    with pytest.raises(RouteError, match=words) as e:
        load_route(p)
    msg = str(e.value)
    assert msg.startswith(str(p))
    if line is not None:
        assert f"line {line}" in msg
    if col is not None:
        assert f"column {col}" in msg


def test_csv_column_named_twice_is_refused(tmp_path):
    p = tmp_path / "dup.csv"
    p.write_text("distance_m,speed_limit_km_h,Distance_m\n0,25,5\n100,25,6\n")
    with pytest.raises(RouteError, match=r"line 1: column distance_m appears 2 times") as e:
        load_route(p)
    assert str(e.value).startswith(str(p))
    q = tmp_path / "notes.csv"  # columns that are not read may repeat
    q.write_text("distance_m,note,speed_limit_km_h,note\n0,a,25,b\n100,c,25,d\n")
    assert float(load_route(q).length) == 100
    q = tmp_path / "trailing.csv"  # empty cells past the header's (a spreadsheet's export)
    q.write_text("distance_m,speed_limit_km_h\n0,25,,\n100,25,\n")
    assert float(load_route(q).length) == 100


def test_bad_crlf_bom_reports_the_right_line(tmp_path):
    p = tmp_path / "bad.vdri"
    p.write_bytes(b"\xef\xbb\xbf<s>,<v>,<grad>,<stop>\r\n0,50,0,0\r\n100,50,0,0\r\n200,abc,0,0\r\n")
    with pytest.raises(RouteError, match=r"line 4, column <v>: not a number \('abc'\)"):
        load_route(p)


def test_missing_csv_column_and_other_files(tmp_path):
    p = tmp_path / "m.csv"
    p.write_text("distance_m,gradient_pct\n0,0\n100,0\n")
    with pytest.raises(RouteError, match="line 1: missing column speed_limit_km_h"):
        load_route(p)
    q = tmp_path / "x.txt"
    q.write_text(VDRI_TEXT)
    with pytest.raises(RouteError, match="unknown route format"):
        load_route(q)
    with pytest.raises(RouteError, match="no such file"):
        load_route(tmp_path / "nope.vdri")
    with pytest.raises(RouteError, match="no such route file.*short_track"):
        load_route("no_such_route")
    b = tmp_path / "bin.vdri"
    b.write_bytes(b"<s>,<v>\n\xff\xfe\x00\n")
    with pytest.raises(RouteError, match="not UTF-8"):
        load_route(b)


def test_a_directory_or_an_unreadable_file_is_named(tmp_path, monkeypatch):
    """A directory was "unknown route format '.1'" (vecto-3.0.1/) or "''"; a file the system
    cannot read (/proc/self/mem behind a link) was "[Errno 5] Input/output error", no file
    named."""
    for d in (VECTO, ROUTE_DIR, tmp_path):
        with pytest.raises(RouteError, match=f"^{d}: is a directory, not a route file$"):
            load_route(d)
    p = tmp_path / "r.csv"
    p.write_text(CSV_TEXT)

    def broken(self):
        raise OSError(5, "Input/output error")

    monkeypatch.setattr(type(p), "read_bytes", broken)
    with pytest.raises(RouteError, match=rf"^{p}: cannot read \(Input/output error\)$"):
        load_route(p)
