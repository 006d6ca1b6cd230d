"""map_batch against a NumPy loop and jax.vmap; no retrace; 2 host devices in a subprocess."""

import os
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxems.shard import (
    backends_started,
    chunk_plan,
    map_batch,
    one_at_a_time,
    shortcut,
    use_host_devices,
)

TRACES = [0]


def item_fn(shared, item):
    """One item: y = s A x + k, z = 3 damped sine iterations of x, n = count of x > 0."""
    TRACES[0] += 1
    A, s = shared
    y = s * (A @ item["x"]) + item["k"]
    z = jax.lax.fori_loop(0, 3, lambda i, c: 0.5 * c + jnp.sin(c), item["x"])
    return {"y": y, "z": z, "n": jnp.sum(item["x"] > 0).astype(jnp.int32)}


def reference(shared, items):
    """The same with NumPy, one item at a time."""
    A, s = (np.asarray(a) for a in shared)
    out = {"y": [], "z": [], "n": []}
    for x, k in zip(items["x"], items["k"], strict=True):
        out["y"].append(s * (A @ x) + k)
        z = x.copy()
        for _ in range(3):
            z = 0.5 * z + np.sin(z)
        out["z"].append(z)
        out["n"].append(np.sum(x > 0))
    return {key: np.stack(v) for key, v in out.items()}


def batch(B, seed=0):
    rng = np.random.default_rng(seed)
    items = {"x": rng.normal(size=(B, 3)), "k": rng.integers(-5, 5, size=B).astype(float)}
    shared = (rng.normal(size=(3, 3)), np.float64(1.5))
    return items, shared


@pytest.mark.parametrize("B,chunk", [(11, 3), (7, None), (1, 4), (8, 8), (5, 1)])
def test_map_batch_matches_loop_and_vmap(B, chunk):
    items, shared = batch(B)
    out = map_batch(item_fn, items, shared=shared, chunk=chunk)
    ref = reference(shared, items)
    vm = jax.vmap(lambda it: item_fn(shared, it))(items)
    for key in ref:
        assert out[key].shape[0] == B
        np.testing.assert_allclose(np.asarray(out[key]), ref[key], rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(np.asarray(out[key]), np.asarray(vm[key]), rtol=1e-13,
                                   atol=1e-13)
    assert out["y"].dtype == jnp.float64


def test_no_shared_and_no_retrace():
    items, shared = batch(11, seed=1)

    def fn(item):
        return item_fn(shared, item)

    out = map_batch(fn, items, chunk=4)
    n = TRACES[0]
    items2, _ = batch(11, seed=2)  # new values, same shapes: the cached program runs
    out2 = map_batch(fn, items2, chunk=4)
    assert TRACES[0] == n
    np.testing.assert_allclose(np.asarray(out["y"]), reference(shared, items)["y"], rtol=1e-12)
    np.testing.assert_allclose(np.asarray(out2["y"]), reference(shared, items2)["y"],
                               rtol=1e-12)
    map_batch(fn, batch(12)[0], chunk=4)  # another batch size traces again (one shape more)
    assert TRACES[0] > n


def test_shared_values_do_not_retrace():
    items, shared = batch(6, seed=3)
    map_batch(item_fn, items, shared=shared, chunk=4)
    n = TRACES[0]
    shared2 = (shared[0] * 2.0, np.float64(-0.5))
    out = map_batch(item_fn, items, shared=shared2, chunk=4)
    assert TRACES[0] == n
    np.testing.assert_allclose(np.asarray(out["y"]), reference(shared2, items)["y"], rtol=1e-12)


@pytest.mark.parametrize("B,n,chunk", [(1, 1, 4), (11, 1, 3), (1000, 2, 64), (32, 2, 64),
                                        (65, 2, 8), (7, 4, None)])
def test_chunk_plan_bounds(B, n, chunk):
    c, k = chunk_plan(B, n, chunk)
    total = n * k * c
    assert total >= B
    assert total - B < n * k + n  # padding: less than one item per chunk, plus rounding
    # a chunk never exceeds the requested size (None: one chunk of each device's share)
    assert c >= 1 and c <= (chunk if chunk is not None else -(-B // n))
    assert chunk is not None or k == 1


def test_bad_arguments():
    items, shared = batch(4)
    with pytest.raises(ValueError, match="different leading sizes"):
        map_batch(item_fn, {"x": items["x"], "k": items["k"][:3]}, shared=shared)
    with pytest.raises(ValueError, match="scalar"):
        map_batch(item_fn, {"x": items["x"], "k": np.float64(1.0)}, shared=shared)
    with pytest.raises(ValueError, match="chunk"):
        map_batch(item_fn, items, shared=shared, chunk=0)
    with pytest.raises(ValueError, match="devices"):
        map_batch(item_fn, items, shared=shared, devices=len(jax.devices()) + 1)
    with pytest.raises(ValueError, match="whole number"):
        use_host_devices(0)


def test_use_host_devices_after_start(monkeypatch):
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_enable_fast_math=false")
    have = len(jax.devices("cpu"))  # the backend has started
    assert backends_started() is True
    with pytest.raises(RuntimeError, match="already started"):
        use_host_devices(have + 1)
    assert os.environ["XLA_FLAGS"] == "--xla_cpu_enable_fast_math=false"  # unchanged
    assert use_host_devices(have) == have  # same count: accepted, flag added for children
    assert os.environ["XLA_FLAGS"].split() == ["--xla_cpu_enable_fast_math=false",
                                               f"--xla_force_host_platform_device_count={have}"]


CHILD = textwrap.dedent("""
    import os
    import numpy as np
    from jaxems.shard import backends_started, map_batch, use_host_devices
    assert backends_started() is False  # importing jaxems does not start JAX's backend
    use_host_devices(2)
    assert "--xla_force_host_platform_device_count=2" in os.environ["XLA_FLAGS"]
    assert "--xla_cpu_enable_fast_math=false" in os.environ["XLA_FLAGS"]
    import jax
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    assert len(jax.devices()) == 2, jax.devices()

    def fn(shared, x):
        z = jax.lax.fori_loop(0, 4, lambda i, c: 0.5 * c + jnp.sin(c) * shared, x)
        return {"z": z, "s": jnp.sum(z)}

    x = np.random.default_rng(0).normal(size=(13, 5))
    ref = jax.vmap(lambda a: fn(2.0, a))(x)
    for chunk in (3, None):
        out = map_batch(fn, x, shared=2.0, chunk=chunk)
        assert out["z"].shape == (13, 5), out["z"].shape
        for k in ref:
            np.testing.assert_allclose(np.asarray(out[k]), np.asarray(ref[k]), rtol=1e-13)
    on_one = map_batch(fn, x, shared=2.0, chunk=3, devices=1)
    np.testing.assert_allclose(np.asarray(on_one["z"]), np.asarray(ref["z"]), rtol=1e-13)
    try:
        use_host_devices(3)
    except RuntimeError:
        pass
    else:
        raise AssertionError("use_host_devices(3) after start did not raise")
    print("OK", len(jax.devices()))
""")


def test_two_host_devices_subprocess():
    # host devices are CPU devices: JAX_PLATFORMS keeps a GPU, where one is, out of the child
    env = dict(os.environ, JAX_PLATFORMS="cpu", XLA_FLAGS="--xla_cpu_enable_fast_math=false "
               "--xla_force_host_platform_device_count=7")
    r = subprocess.run([sys.executable, "-c", CHILD], env=env, capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stderr[-3000:]
    assert r.stdout.strip().splitlines()[-1] == "OK 2"


def test_shortcut_runs_the_full_form_only_where_needed():
    # check knows the answer (x + 1) for x >= 0; full (x + 100) counts its runs
    runs = []

    def full(x, k):
        jax.debug.callback(lambda: runs.append(1))
        return x + 100 * k

    f = shortcut(lambda x, k: (x >= 0, x + k), full)
    want = lambda x: np.where(x >= 0, x + 1, x + 100)  # noqa: E731
    one = jax.jit(f)
    assert float(one(2.0, 1.0)) == 3.0 and not runs
    assert float(one(-2.0, 1.0)) == 98.0 and len(runs) == 1
    # under vmap (an unbatched argument; inside jit, scan and lax.map's chunks): full runs
    # once per call where some item needs it, never where none does
    batched = jax.jit(jax.vmap(f, in_axes=(0, None)))
    runs.clear()
    np.testing.assert_array_equal(batched(jnp.arange(4.0), 1.0), np.arange(4.0) + 1)
    assert not runs
    x = jnp.array([1.0, -1.0, 2.0, -3.0])
    np.testing.assert_array_equal(batched(x, 1.0), want(np.asarray(x)))
    assert len(runs) == 1
    np.testing.assert_array_equal(jax.vmap(f)(x, jnp.ones(4)), want(np.asarray(x)))

    def body(c, xi):
        return c, f(xi, 1.0)

    np.testing.assert_array_equal(jax.jit(lambda a: jax.lax.scan(body, 0.0, a)[1])(x),
                                  want(np.asarray(x)))
    for bs in (None, 2):
        np.testing.assert_array_equal(jax.lax.map(lambda xi: f(xi, 1.0), x, batch_size=bs),
                                      want(np.asarray(x)))


def test_one_at_a_time_is_a_loop_under_vmap():
    """A function made `one_at_a_time` gives under `jax.vmap` (batched and unbatched
    arguments, pytrees, nested in jit and lax.map's chunks) what it gives item by item; on a CPU
    (or with sequential=True) its items run one after the other: a while loop whose trip count
    depends on the item runs each item's own count, not the batch's largest (counted by a
    callback); with sequential=False it is vectorised."""
    trips = []

    def f(x, p):  # x: (), p: {"a": (2,), "b": ()}; a while loop of x trips
        def body(c):
            jax.debug.callback(lambda: trips.append(1))
            return c[0] + 1.0, c[1] + p["a"] * c[0]

        n, acc = jax.lax.while_loop(lambda c: c[0] < x, body, (0.0, jnp.zeros(2)))
        return {"n": n, "acc": acc + p["b"]}

    x = jnp.array([3.0, 0.0, 5.0, 1.0])
    p = {"a": jnp.array([1.0, 2.0]), "b": jnp.array([0.5, -1.0, 2.0, 0.0])}
    want = [f(xi, {"a": p["a"], "b": bi}) for xi, bi in zip(x, p["b"], strict=True)]
    # one at a time: 9 trips in all (each item's own); vectorised: the batch's 5 (once each)
    for g, n_trips in ((one_at_a_time(f), 9 if jax.default_backend() == "cpu" else 5),
                       (one_at_a_time(f, sequential=True), 9),
                       (one_at_a_time(f, sequential=False), 5)):
        for batched in (jax.jit(jax.vmap(g, in_axes=(0, {"a": None, "b": 0}))),
                        lambda x, p, g=g: jax.lax.map(
                            lambda xb: g(xb[0], {"a": p["a"], "b": xb[1]}), (x, p["b"]),
                            batch_size=4)):
            trips.clear()
            out = batched(x, p)
            for i, w in enumerate(want):
                for k in w:
                    np.testing.assert_array_equal(np.asarray(out[k][i]), np.asarray(w[k]))
            assert len(trips) == n_trips
        # unbatched: f itself
        assert float(jax.jit(g)(2.0, {"a": p["a"], "b": 1.0})["n"]) == 2.0


LEVEL2_CHILD = textwrap.dedent("""
    import numpy as np
    from jaxems.shard import map_batch, use_host_devices
    use_host_devices(2)
    import jax
    import jax.numpy as jnp
    from jaxems import strategies as S
    from jaxems.io import load_route
    from jaxems.levels import battery as l2
    from jaxems.params import load_vehicle, stack_vehicles

    route = load_route("LongHaul")
    base = load_vehicle()
    vps = stack_vehicles([base.replace(mass=15e3, E_b_max=e * 1e6) for e in (1, 2, 3, 4)])
    vps = jax.tree.map(lambda a: np.asarray(a, np.float32), vps)
    n = S.steps_for_batch(route, vps)

    def fn(route, vp):
        p = S.level3(route, vp, 1.0, n)
        c2 = l2.costate_kernel(vp, p.P_d, p.v, jnp.full_like(p.v, vp.w_pred), p.mask, 1.0,
                               max_pieces=32)
        return c2.n_pieces, c2.lam0

    sharded = map_batch(fn, vps, shared=route, chunk=4)
    alone = [jax.jit(fn)(route, jax.tree.map(lambda a: a[i], vps)) for i in range(4)]
    np.testing.assert_array_equal(np.asarray(sharded[0]), [int(a[0]) for a in alone])
    np.testing.assert_allclose(np.asarray(sharded[1]), [float(a[1]) for a in alone], rtol=1e-5)
    print("OK", np.asarray(sharded[0]).tolist())
""")


def test_level2_in_a_chunk_over_two_host_devices_subprocess():
    """Level 2 on Long Haul in a sweep's vmapped chunk over two host devices (float32) equals
    Level 2 of each configuration alone: its pieces (the battery's limits, which a bracket
    evaluated on the other side of a guard once made it drop: one piece for every battery
    size, `battery.bracket_held`) and its costate."""
    env = dict(os.environ, JAX_PLATFORMS="cpu", XLA_FLAGS="--xla_cpu_enable_fast_math=false")
    r = subprocess.run([sys.executable, "-c", LEVEL2_CHILD], env=env, capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    assert r.stdout.strip().splitlines()[-1].startswith("OK")
