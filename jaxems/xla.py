"""How jaxems compiles its programs: `jit`, `jax.jit` with the XLA code generator chosen.

XLA's CPU backend generates the machine code of each fused kernel with one of two code
generators: its newer MLIR fusion emitters (XLA's default) or its older elemental emitters
(compiler option ``xla_cpu_use_fusion_emitters=False``). jaxems' programs are long chains of
small fusions inside loops (Level 2's bisection, the Viterbi DPs, the plant's step). Most of
them compile in up to 25 % less time with the elemental emitters, run as fast, and a batch
needs about half the memory. The results are equal to the last bit, or 1-2 ulp apart. The
programs that run slower with them (the MPC, the eco-driving, the conventional truck's batch)
keep XLA's default: `jit(..., elemental=False)`, chosen per strategy in `strategies`. The
figures, and the commands that give them, are in the README ("Compilation").

`jit(fun, **jax_jit_keywords)` is `jax.jit` with that option; the option names a CPU code
generator, so other backends (GPU) ignore it. A JAX whose XLA does not know the option
compiles with its defaults: `compiler_options()` checks once, with a one-line program, on the
first call of a jitted function (not at import, which must not start JAX's backend: see
`shard.use_host_devices`).
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import jax
import numpy as np

ELEMENTAL = {"xla_cpu_use_fusion_emitters": False}  # XLA's older CPU code generator


@functools.cache
def compiler_options() -> dict | None:
    """`ELEMENTAL` if this JAX's XLA knows the option, else None (XLA's defaults)."""
    try:
        jax.jit(lambda x: x, compiler_options=ELEMENTAL).lower(np.float32(0.0)).compile()
    except Exception:  # noqa: BLE001 - an unknown option (older or newer XLA): defaults
        return None
    return dict(ELEMENTAL)


class _Jit:
    """`jax.jit(fun, ...)` built on the first use, when `compiler_options` can be checked."""

    def __init__(self, fun: Callable, elemental: bool, kw: dict):
        functools.update_wrapper(self, fun)
        self._fun, self._elemental, self._kw = fun, elemental, kw
        self._jitted = None

    def _get(self):
        if self._jitted is None:
            opts = compiler_options() if self._elemental else None
            self._jitted = jax.jit(self._fun, compiler_options=opts, **self._kw)
        return self._jitted

    def __call__(self, *args, **kwargs):
        return self._get()(*args, **kwargs)

    def __getattr__(self, name):  # lower, trace, eval_shape, clear_cache, ...
        if name.startswith("__") or name in ("_fun", "_elemental", "_kw", "_jitted"):
            raise AttributeError(name)
        return getattr(self._get(), name)


def jit(fun: Callable | None = None, /, *, elemental: bool = True, **kw):
    """`jax.jit(fun, **kw)` compiled with XLA's elemental CPU emitters (`elemental=True`,
    where this XLA has them) or with XLA's defaults (`elemental=False`).

    Usable as `jit(f, static_argnames=...)` or as a decorator, `@jit` or
    `@jit(static_argnames=...)`. The result calls, lowers and traces as `jax.jit`'s does.
    """
    if fun is None:
        return functools.partial(jit, elemental=elemental, **kw)
    return _Jit(fun, elemental, kw)
