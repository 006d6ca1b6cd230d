"""Tests run in float64 (sweeps run float32 by default); matplotlib without a display.

One persistent JAX compilation cache serves the whole run: the pytest-xdist workers, and the
processes tests start (CLI runs, sweep workers), load what another process compiled instead
of compiling it again (it saves compile time only; results are the same). The directory is made
for the run and removed after it, so every run is timed from a cold cache, as CI's is; set
JAX_COMPILATION_CACHE_DIR to keep one between runs.

Tests jit the library's functions with `jaxems.xla.jit`, as the library does (XLA's elemental
CPU emitters: the suite compiles in about a quarter less time).

`make test` hands whole files to two workers in collection order (pytest-xdist's loadfile,
--no-loadscope-reorder), and the collection is ordered here: the longest compilations first,
one per worker, and last the files that run what test_strategies.py has compiled by then (the
short track's strategies, which they load from the cache).
"""

import functools
import os
import shutil
import tempfile

os.environ.setdefault("MPLBACKEND", "Agg")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

from hypothesis import settings, strategies  # noqa: E402

settings.register_profile("jaxems", max_examples=40, deadline=None, derandomize=True)
# `make test-random` (pytest --hypothesis-profile=random [--hypothesis-seed=N]): new examples
# each run, the property tests' own numbers of them; what a fixed set never draws
settings.register_profile("random", parent=settings.get_profile("jaxems"), derandomize=False,
                          database=None, print_blob=True)
settings.load_profile("jaxems")


def _no_subnormal_floats():
    """Property tests draw no subnormal floats unless one asks for them: XLA on a CPU flushes
    them to zero, NumPy does not, and every property test compares a kernel with a NumPy loop
    (a demand of 2e-309 W is 0 W to the kernel and a positive demand to the loop, which then
    forbids the modes that only coast; found by random-seed runs, one test at a time before).
    Nor the smallest normal ones: where 0 lies in the range, a draw below 1e-200 in magnitude
    is 0 (2.2e-308 W of demand, times an efficiency or over a mass, is subnormal again:
    `make test-random SEED=31`, test_protection_equals_its_loop)."""
    floats = strategies.floats

    @functools.wraps(floats)
    def normal_floats(min_value=None, max_value=None, *args, allow_subnormal=False, **kwargs):
        drawn = floats(min_value, max_value, *args, allow_subnormal=allow_subnormal, **kwargs)
        if allow_subnormal or (min_value is not None and min_value > 0) or (
                max_value is not None and max_value < 0):
            return drawn
        return drawn.map(lambda x: 0.0 if abs(x) < 1e-200 else x)

    strategies.floats = normal_floats


_no_subnormal_floats()


def _no_local_constants():
    """Derandomized examples that depend on the test alone. Hypothesis also draws, now and
    then, numbers written in the source of the modules imported so far (its "local
    constants"), so a test's examples changed with the files a worker had run before it and
    with any edit to the library: test_route's brute-force grid failed when run alone and
    passed in the whole suite. Its private hook is replaced by the empty pool where this
    Hypothesis has one (elsewhere the suite runs as before)."""
    try:
        from hypothesis.internal.conjecture import providers
    except ImportError:
        return
    if hasattr(providers, "_get_local_constants") and hasattr(providers, "_local_constants"):
        empty = providers._local_constants
        providers._get_local_constants = lambda: empty


_no_local_constants()

CACHE_ENV = "JAX_COMPILATION_CACHE_DIR"


def pytest_configure(config):
    # the controller (or a run without xdist) makes the directory; workers inherit the variable
    if not hasattr(config, "workerinput") and not os.environ.get(CACHE_ENV):
        config._jaxems_cache = os.environ[CACHE_ENV] = tempfile.mkdtemp(prefix="jaxems-jax-")
    jax.config.update("jax_compilation_cache_dir", os.environ[CACHE_ENV])


def pytest_unconfigure(config):
    made = getattr(config, "_jaxems_cache", None)
    if made is not None:
        shutil.rmtree(made, ignore_errors=True)
        del os.environ[CACHE_ENV]


FIRST = ("test_strategies.py", "test_eco.py", "test_battery.py", "test_level1.py",
         "test_plant.py", "test_reference.py")
LAST = ("test_experiments.py", "test_cli_simulate.py", "test_cli.py", "test_demo.py",
        "test_sweep.py", "test_sweep_kill.py")


def pytest_collection_modifyitems(items):
    def rank(item):
        name = item.path.name
        if name in FIRST:
            return FIRST.index(name)
        return len(FIRST) + (1 + LAST.index(name) if name in LAST else 0)

    items.sort(key=rank)  # stable: within a file, the file's own order
