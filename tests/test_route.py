"""Route grid construction from sparse rows, padding, elevation (brute-force references)."""

import numpy as np
import pytest
from hypothesis import example, given
from hypothesis import strategies as st

from jaxems.route import (
    BUCKET,
    Route,
    RouteError,
    Row,
    check_route,
    check_rows,
    elevation,
    n_nodes,
    node_positions,
    pad_route,
    pad_routes,
    route_from_rows,
    route_summary,
    unstack_routes,
)

COLS = ("s", "v", "grad", "stop")


def rows(*data):
    return [Row(*r, line=i + 2) for i, r in enumerate(data)]


def _source_functions(rs):
    """Brute-force lookups of the source rows (vectorised): limit(s) m/s, grade(s) rise/run."""
    s = np.array([r.s_m for r in rs]) - rs[0].s_m
    v = np.array([r.v_kmh for r in rs]) / 3.6
    g = np.array([r.grad_pct for r in rs]) / 100
    eff = v.copy()
    for j in range(len(v)):  # stop row: the stretch up to the next row has the next moving speed
        k = j
        while eff[j] == 0 and k + 1 < len(v):
            k += 1
            eff[j] = v[k]
        if eff[j] == 0:  # no moving row after it: the previous stretch's limit
            eff[j] = eff[j - 1]

    def seg(x):
        return np.minimum(np.searchsorted(s, x, side="right") - 1, len(s) - 2)

    return (lambda x: eff[seg(x)]), (lambda x: g[seg(x)])


def test_grid_nodes_and_length():
    r = route_from_rows(rows((0, 50, 0, 0), (1055, 50, 0, 0)), ds=10.0, bucket=None)
    n = n_nodes(r)
    assert n == 107  # ceil(1055 / 10) cells
    assert float(r.ds) == pytest.approx(1055 / 106)
    assert float(r.ds) <= 10.0
    assert float(r.length) == 1055.0
    assert node_positions(r)[n - 1] == pytest.approx(1055.0)
    # exact multiple: no shrinking
    r2 = route_from_rows(rows((100, 50, 0, 0), (300, 50, 0, 0)), ds=10.0, bucket=None)
    assert n_nodes(r2) == 21 and float(r2.ds) == 10.0 and float(r2.length) == 200.0


def test_bucket_padding():
    r = route_from_rows(rows((0, 50, 3, 0), (1000, 50, 0, 0)), ds=10.0)
    assert r.grade.shape == (BUCKET,)
    assert n_nodes(r) == 101
    assert not r.mask[101:].any() and r.mask[:101].all()
    assert (r.grade[100:] == 0).all() and (r.stop[101:] == 0).all()


@given(
    st.lists(
        st.tuples(
            st.floats(3.0, 300.0),  # distance increment
            st.sampled_from([0.0, 10.0, 30.0, 50.0, 85.0]),  # speed (0 = stop)
            st.floats(-12.0, 12.0),  # grade %
            st.floats(1.0, 60.0),  # stop duration if a stop
        ),
        min_size=2,
        max_size=8,
    ),
    st.sampled_from([2.0, 5.0, 10.0, 25.0]),
)
def test_grid_against_brute_force(spec, ds):
    s = np.cumsum([0.0] + [d for d, *_ in spec[1:]])
    data = []
    for k, (_, v, g, stop) in enumerate(spec):
        data.append((float(s[k]), v, g, stop if v == 0 else 0.0))
    if all(v == 0 for _, v, _, _ in data[:-1]):
        data[0] = (data[0][0], 50.0, data[0][2], 0.0)
    rs = rows(*data)
    r = route_from_rows(rs, ds=ds, bucket=None)
    limit, grade = _source_functions(rs)
    n = n_nodes(r)
    x = node_positions(r)
    dsr = float(r.ds)
    L = float(r.length)
    assert L == pytest.approx(s[-1])
    # elevation (tan form) at every node equals a fine quadrature of the source gradient
    fine = np.linspace(0, L, 20001)
    mid = 0.5 * (fine[1:] + fine[:-1])
    rise_fine = np.concatenate([[0], np.cumsum(grade(mid) * np.diff(fine))])
    rise_nodes = np.concatenate([[0], np.cumsum(r.grade[: n - 1] * dsr)])
    np.testing.assert_allclose(rise_nodes, np.interp(x[:n], fine, rise_fine), atol=0.02 * dsr)
    # speed limit at a node = the smallest source limit within one cell either side
    probe = np.linspace(-1, 1, 401)[1:-1]
    s_rows = np.array([row.s_m for row in rs]) - rs[0].s_m
    for i in range(n):
        near = s_rows[(s_rows > x[i] - dsr) & (s_rows < x[i] + dsr)]  # every segment that starts
        # and every one that ends within the cells, however little of it lies in them (a
        # segment ending 0.05 m into a 24 m cell fell between the probes)
        ends = near[near - 1e-7 > x[i] - dsr] - 1e-7
        p = np.clip(np.concatenate([x[i] + probe * dsr, near, ends]), 0, L * (1 - 1e-12))
        assert r.vmax[i] == pytest.approx(limit(p).min(), abs=1e-9)
    # stops: at the node nearest each stop row, durations add up
    stop_ref = np.zeros(n)
    for row in rs:
        if row.v_kmh == 0:
            stop_ref[int(np.clip(np.rint((row.s_m - rs[0].s_m) / dsr), 0, n - 1))] += row.stop_s
    np.testing.assert_allclose(r.stop[:n], stop_ref)


@example([(0.0, 0.0), (0.001, 30.0), (200.0, 0.0)], 10.0)
@given(
    st.lists(st.tuples(st.floats(0.001, 300.0), st.sampled_from([-30.0, 30.0, 29.99, 0.0])),
             min_size=2, max_size=6),
    st.sampled_from([2.0, 5.0, 10.0, 25.0]),
)
def test_rows_at_the_gradient_limit_give_a_route_within_it(spec, ds):
    """A cell's gradient is the mean of its rows', so rows within +-30 % give cells within it:
    rounding may not take one past, where `check_route` (the API's own check) refuses it (a
    30 % row gave a cell of 0.30000000000000016)."""
    s = np.cumsum([0.0] + [d for d, _ in spec[1:]])
    data = [(float(s[k]), 50.0, g, 0.0) for k, (_, g) in enumerate(spec)]
    r = route_from_rows(rows(*data, (float(s[-1]) + 100.0, 50.0, 0.0, 0.0)), ds=ds, bucket=None)
    assert check_route(r) is r
    assert float(np.max(np.abs(r.grade))) <= 0.3


def test_stop_row_takes_next_speed_and_start_end_flags():
    r = route_from_rows(
        rows((0, 0, 0, 5), (100, 40, 0, 0), (300, 0, 0, 20), (400, 60, 0, 0), (600, 0, 0, 3)),
        ds=10.0,
        bucket=None,
    )
    kmh = 1 / 3.6
    assert r.stop[0] == 5 and r.stop[30] == 20 and r.stop[60] == 3
    # stretch 0..100 after the starting stop has the next row's 40 km/h
    assert r.vmax[5] == pytest.approx(40 * kmh)
    assert r.vmax[35] == pytest.approx(60 * kmh)  # after the stop at 300: the 400 m row's speed
    info = route_summary(r)
    assert info["starts_stopped"] and info["ends_stopped"]
    assert info["stops"] == 3 and info["stop_time_s"] == 28


def test_stop_stretch_limit_is_next_moving_row():
    # the stop at 300 is followed by the 400 m row (60 km/h): 300..400 is 60 km/h
    r = route_from_rows(
        rows((0, 40, 0, 0), (300, 0, 0, 10), (400, 60, 0, 0), (500, 60, 0, 0)), ds=10.0, bucket=None
    )
    assert r.vmax[32] == pytest.approx(60 / 3.6)
    assert r.vmax[25] == pytest.approx(40 / 3.6)


@pytest.mark.parametrize(
    "data,col,what",
    [
        ([], None, "empty"),
        ([(0, 50, 0, 0)], None, "only one data row"),
        ([(0, 50, 0, 0), (0, 50, 0, 0)], "s", "distance not increasing"),
        ([(0, 50, 0, 0), (100, 50, 0, 0), (50, 50, 0, 0)], "s", "distance not increasing"),
        ([(0, -5, 0, 0), (100, 50, 0, 0)], "v", "negative speed"),
        ([(0, 201, 0, 0), (100, 50, 0, 0)], "v", "above 200"),
        ([(0, 50, 30.5, 0), (100, 50, 0, 0)], "grad", "beyond"),
        ([(0, 50, -31, 0), (100, 50, 0, 0)], "grad", "beyond"),
        ([(0, 0, 0, 0), (100, 50, 0, 0)], "stop", "no duration"),
        ([(0, 50, 0, -1), (100, 50, 0, 0)], "stop", "negative stop"),
        ([(0, 50, 0, 5), (100, 50, 0, 0)], "stop", "a stop row has speed 0"),
        ([(0, 50, float("nan"), 0), (100, 50, 0, 0)], "grad", "not a finite number"),
        ([(0, 0, 0, 4), (100, 0, 0, 4)], None, "never moves"),
        ([(0, 0, 0, 4), (50, 0, 0, 4), (100, 0, 0, 4)], None, "never moves"),
    ],
)
def test_check_rows_errors(data, col, what):
    rs = rows(*data)
    with pytest.raises(RouteError, match=what) as e:
        check_rows(rs, "f.vdri", COLS)
    msg = str(e.value)
    assert msg.startswith("f.vdri")
    if col:
        assert f"column {col}" in msg and "line" in msg


def test_ds_out_of_range():
    for ds in (0.5, 101.0, float("nan")):
        with pytest.raises(RouteError, match="ds must be"):
            route_from_rows(rows((0, 50, 0, 0), (100, 50, 0, 0)), ds=ds)


def test_pad_routes_and_unstack():
    a = route_from_rows(rows((0, 50, 2, 0), (700, 50, 0, 0)), bucket=None)
    b = route_from_rows(rows((0, 0, -1, 3), (6000, 80, 0, 0)), bucket=None)
    batch = pad_routes([a, b], bucket=256)
    assert isinstance(batch, Route)
    assert batch.grade.shape == (2, 768) and batch.ds.shape == (2,)
    back = unstack_routes(batch)
    for orig, got in zip((a, b), back, strict=True):
        n = n_nodes(orig)
        assert n_nodes(got) == n
        for x, y in zip(orig, got, strict=True):
            x, y = np.asarray(x), np.asarray(y)
            if x.ndim:
                np.testing.assert_array_equal(x[:n], y[:n])
            else:
                assert x == y
        assert got.vmax[n:].min() == orig.vmax[n - 1]  # padding continues the last limit
    with pytest.raises(RouteError):
        pad_routes([])
    with pytest.raises(RouteError, match="cannot pad"):
        pad_route(b, 10)


def test_elevation_sin_of_slope():
    r = route_from_rows(rows((0, 50, 10, 0), (100, 50, -10, 0), (200, 50, 0, 0)), bucket=None)
    h = elevation(r)
    n = n_nodes(r)
    assert h[10] == pytest.approx(100 * np.sin(np.arctan(0.1)))
    assert h[n - 1] == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize(
    "field,node,value,why",
    [
        ("grade", 3, np.nan, "finite rise/run"),
        ("grade", 3, 0.45, "within"),
        ("vmax", 0, -7.0, "speed limit"),
        ("vmax", 5, np.inf, "speed limit"),
        ("stop", 2, -1.0, "standstill time"),
        ("ds", None, 0.0, "finite distance"),
        ("length", None, np.nan, "distance from"),
        ("length", None, 1e9, "distance from"),
        ("vmax", 4, 0.1, "speed limit"),
        ("stop", 2, 1e20, "standstill time"),
    ],
)
def test_check_route_names_the_field_and_the_node(field, node, value, why):
    """Routes built or changed in Python are held to a route file's rules at the API; the
    padding beyond the mask is not checked; in a batch the index is [route, node]."""
    import jaxems

    r = jaxems.load_route("short_track")
    assert check_route(r) is r
    x = np.array(getattr(r, field), dtype=float)
    if node is None:
        x = np.float64(value)
        at = ""
    else:
        x[node] = value
        at = rf"\[{node}\]"
    bad = r._replace(**{field: x})
    with pytest.raises(RouteError, match=rf"^route {field}{at}: .*{why}"):
        check_route(bad)
    if node is not None:
        with pytest.raises(RouteError, match=rf"^route {field}\[1, {node}\]: .*{why}"):
            check_route(pad_routes([r, bad]))
        with pytest.raises(RouteError, match=rf"^route {field}"):  # the API checks first
            jaxems.predict_velocity(bad, jaxems.load_vehicle())
    padded = np.array(r.grade, dtype=float)
    padded[~np.asarray(r.mask)] = np.nan  # beyond the route: not read, not checked
    check_route(r._replace(grade=padded))


def _hole(mask):
    m = np.array(mask)
    m[50:60] = False
    return m


@pytest.mark.parametrize(
    "change, field, why",
    [
        (lambda r, N: {"mask": np.zeros(N, bool)}, "mask", "at least 2 nodes"),
        (lambda r, N: {"mask": np.arange(N) < 1}, "mask", "at least 2 nodes"),
        (lambda r, N: {"mask": _hole(r.mask)}, "mask", "first nodes"),
        (lambda r, N: {"mask": np.asarray(r.mask, float)}, "mask", "booleans"),
        (lambda r, N: {"length": float(r.length) / 2}, "length", r"\(kept nodes - 1\) \* ds"),
        (lambda r, N: {"ds": 1.0}, "length", r"\(kept nodes - 1\) \* ds = 106 m"),
        (lambda r, N: {"ds": np.full(N, float(r.ds))}, "ds", "shape"),
        (lambda r, N: {"vmax": np.full(100, 5.0)}, "vmax", "grade's shape"),
        (lambda r, N: {k: np.zeros(0) for k in ("grade", "vmax", "stop")}
         | {"mask": np.zeros(0, bool)}, "grade", "at least 2 nodes"),
        (lambda r, N: {"grade": None}, "grade", "array of numbers"),
        (lambda r, N: {"stop": "abc"}, "stop", "array of numbers"),
    ],
)
def test_check_route_holds_the_arrays_together(change, field, why):
    """A route built or changed in Python whose arrays do not fit together (no nodes kept, a
    hole in the mask, a length that is not its nodes' span, shapes apart, leaves that are not
    numbers) is a RouteError naming the field, at the API too; before, each of these ran to a
    result marked ok (half a route's fuel for half its length) or failed inside JAX."""
    import jaxems

    r = jaxems.load_route("short_track")
    bad = r._replace(**change(r, r.grade.shape[0]))
    with pytest.raises(RouteError, match=rf"^route {field}(\[\d+\])?: .*{why}"):
        check_route(bad)
    with pytest.raises(RouteError, match=rf"^route {field}"):
        jaxems.simulate(bad, strategy="conventional")


def test_check_route_takes_lists_and_the_api_one_route():
    """Leaves given as lists are made arrays (they ran into JAX as pytrees of numbers); a
    batch of routes where the API runs one is refused by name."""
    import jaxems

    r = jaxems.load_route("short_track")
    as_lists = r._replace(grade=list(np.asarray(r.grade)), ds=float(r.ds))
    got = check_route(as_lists)
    assert isinstance(got.grade, np.ndarray) and got.grade.shape == r.grade.shape
    np.testing.assert_array_equal(got.grade, r.grade)
    with pytest.raises(RouteError, match="^route: one route expected"):
        jaxems.simulate(pad_routes([r, r]), strategy="conventional")
