"""`xla.jit`: jax.jit with XLA's elemental CPU emitters, same results, fallback to defaults."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxems import xla
from jaxems.levels import level1 as l1


def _kernel(x, n):
    # a scan of small fused steps, as jaxems' kernels are
    def step(c, xi):
        c = jnp.where(xi > c, 0.5 * (c + xi), c * 0.99 + jnp.sin(xi))
        return c, jnp.exp(-c) * xi
    return jax.lax.scan(step, x[0], x[:n])


def test_jit_equals_jax_jit_and_keeps_the_function():
    x = jnp.linspace(-2.0, 3.0, 64)
    f = xla.jit(_kernel, static_argnames=("n",))
    g = jax.jit(_kernel, static_argnames=("n",), compiler_options=None)
    for a, b in zip(jax.tree.leaves(f(x, n=50)), jax.tree.leaves(g(x, n=50)), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-14, atol=0)
    assert f.__wrapped__ is _kernel and f.__name__ == "_kernel"
    assert "stablehlo.while" in f.lower(x, n=50).as_text()  # lower, trace: jax.jit's

    @xla.jit
    def h(x):
        return 2 * x

    @xla.jit(static_argnames=("k",))
    def hk(x, k):
        return k * x

    np.testing.assert_array_equal(h(x), 2 * x)
    np.testing.assert_array_equal(hk(x, k=3), 3 * x)


def test_compiler_options_reach_jax_jit(monkeypatch):
    seen = []
    real = jax.jit

    def spy(fun, **kw):
        seen.append(kw.get("compiler_options"))
        return real(fun, **kw)

    monkeypatch.setattr(xla.jax, "jit", spy)
    xla.jit(lambda x: x + 1)(1.0)
    xla.jit(lambda x: x + 1, elemental=False)(1.0)
    assert seen[-2:] == [xla.compiler_options(), None]
    # the check is right: the option is used exactly where this JAX's XLA compiles with it
    try:
        real(lambda x: x, compiler_options=xla.ELEMENTAL).lower(0.0).compile()
        known = True
    except Exception:  # noqa: BLE001
        known = False
    assert xla.compiler_options() == (xla.ELEMENTAL if known else None)


def test_unknown_option_falls_back_to_xla_defaults(monkeypatch):
    before = xla.compiler_options()
    monkeypatch.setattr(xla, "ELEMENTAL", {"xla_cpu_no_such_option_in_any_xla": False})
    xla.compiler_options.cache_clear()
    try:
        assert xla.compiler_options() is None
        np.testing.assert_array_equal(xla.jit(lambda x: x * 3)(np.arange(3.0)), [0.0, 3.0, 6.0])
    finally:
        xla.compiler_options.cache_clear()
    monkeypatch.undo()
    assert xla.compiler_options() == before


def test_the_library_compiles_with_it():
    # the jitted entry points of the levels and the strategies are `xla.jit`s
    from jaxems import strategies
    from jaxems.levels import battery, velocity
    for f in (l1._level1_kernel_jit, l1._level1_mpc_jit, battery._costate_jit,
              velocity._profile_jit, *strategies._RUN.values()):
        assert isinstance(f, xla._Jit), f
    assert [f._elemental for f in strategies._RUN.values()] == [True, False]


class _Stop(Exception):
    pass


def test_strategies_pick_the_code_generator_per_strategy(monkeypatch):
    from jaxems import load_vehicle, shard, stack_vehicles
    from jaxems import strategies as S
    from jaxems.io import load_route
    called = []
    monkeypatch.setattr(S, "_RUN", {e: (lambda *a, e=e, **k: called.append(e))
                                    for e in (True, False)})
    for name in S.STRATEGIES:
        S._run_one(None, None, None, strategy=name, dt=1.0, n_steps=1, opts=S.Options())
    assert called == [S.SINGLE_ELEMENTAL[name] for name in S.STRATEGIES]

    def spy(fn, args, *, elemental, **kw):
        raise _Stop(elemental)

    monkeypatch.setattr(shard, "map_batch", spy)
    route, vps = load_route("short_track"), stack_vehicles([load_vehicle()] * 2)
    for name in S.STRATEGIES:
        with pytest.raises(_Stop) as e:
            S.simulate_batch(route, vps, name, n_steps=256)
        assert e.value.args == (S.BATCH_ELEMENTAL[name],)
    # measured (README, "Compilation"): the MPC, the eco-driving and the conventional truck's
    # batch run faster with XLA's default emitters
    assert not any((S.SINGLE_ELEMENTAL["multilevel-mpc"], S.SINGLE_ELEMENTAL["multilevel-eco"],
                    S.BATCH_ELEMENTAL["conventional"]))


@pytest.mark.parametrize("elemental", [True, False])
def test_map_batch_compiles_with_the_choice(monkeypatch, elemental):
    from jaxems import shard
    seen = []
    real = xla.jit

    def spy(fun, **kw):
        seen.append(kw.get("elemental"))
        return real(fun, **kw)

    monkeypatch.setattr(shard, "jit", spy)
    shard._program.cache_clear()
    fn = functools.partial(jnp.multiply, 2.0)
    out = shard.map_batch(fn, np.arange(4.0), chunk=2, devices=1, elemental=elemental)
    np.testing.assert_array_equal(out, [0.0, 2.0, 4.0, 6.0])
    assert seen == [elemental]
