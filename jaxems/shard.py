"""Fleet batches over host devices with bounded memory: `use_host_devices` and `map_batch`.

XLA's CPU backend shows one device by default, and one device runs one batched program at a
time: a `jax.vmap` over a fleet keeps one core busy for most of the work (the Level 1 DP, the
plant's `lax.scan`). `use_host_devices(n)` asks XLA for n CPU devices (one per core); it must
run before JAX's backend starts (before the first array, `jax.devices()` or jitted call).

`map_batch(fn, args, shared=..., chunk=C)` applies a function of ONE item to a batch:

- the batch (leading axis B on every leaf of `args`) is split evenly over the devices with
  `jax.shard_map` on a 1-D mesh (axis ``"batch"``); with one device there is no shard_map;
- on each device `jax.lax.map(..., batch_size=c)` runs the device's share in vmapped chunks of
  c <= C items one after the other, so the working memory of a device is that of c items, not
  of its whole share (the outputs of all items are still kept: B x the output size); chunks of
  one item run unbatched (`lax.map` without a batch size: plain while loops, which a vmapped
  chunk, even of one, runs as batched loops of selects);
- the batch is padded by repeating its last item so that every device gets the same whole
  number of chunks; padded results are dropped. The chunk size c is balanced: with
  b = ceil(B / n_devices) items per device and k = ceil(b / C) chunks, c = ceil(b / k), so the
  padding is less than k items per device (not up to n_devices * C - 1 items);
- `shared` arguments (a route, switching-cost parameters) are the same for every item and are
  replicated to every device.

Outputs are gathered: when the batch was padded, the result is sliced back to B inside the
jitted program and every device holds the whole (B, ...) result, which is what per-item metrics
need; a function with large per-item outputs (traces) should return less.

On this 2-core CPU one XLA device already spreads parts of a kernel over both cores (XLA's
intra-op threads); two host devices keep both busy for the rest (see docs/bench/). Memory grows
with the items in flight: devices x chunk.

Compilation: the jitted program is cached per (fn, chunk, devices, with/without shared), and
`jax.jit` caches per argument shapes and dtypes, so repeated calls with the same function
object and shapes do not trace again. Pass the same function object each time (a lambda built
anew per call is a new function and traces again).
"""

from __future__ import annotations

import functools
import math
import os
import re
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, PartitionSpec

from .xla import jit

AXIS = "batch"  # name of the mesh axis the batch is split over
_FLAG = "--xla_force_host_platform_device_count"
_FLAG_RE = re.compile(r"--xla_force_host_platform_device_count=\S*")


def _backends_initialised() -> bool | None:
    """True when JAX's backends exist already; None when this JAX version cannot tell."""
    try:
        from jax._src import xla_bridge
    except ImportError:  # pragma: no cover - layout of other JAX versions
        return None
    fn = getattr(xla_bridge, "backends_are_initialized", None)
    if fn is None:  # pragma: no cover
        backends = getattr(xla_bridge, "_backends", None)
        return None if backends is None else bool(backends)
    return bool(fn())


def backends_started() -> bool | None:
    """Whether JAX's backends have started in this process (after that, the CPU device count
    is fixed); None when this JAX version cannot tell. Never starts them itself."""
    return _backends_initialised()


def host_device_count() -> int:
    """Number of CPU devices of the running backend (starts the backend if needed)."""
    return len(jax.devices("cpu"))


def _set_xla_flag(n: int) -> None:
    flags = _FLAG_RE.sub("", os.environ.get("XLA_FLAGS", "")).split()
    os.environ["XLA_FLAGS"] = " ".join([*flags, f"{_FLAG}={n}"])


def use_host_devices(n: int) -> int:
    """Make XLA's CPU backend expose `n` devices (n >= 1); returns n.

    Sets ``XLA_FLAGS=... --xla_force_host_platform_device_count=n`` (added to the flags already
    there, replacing an earlier device count; child processes such as sweep workers inherit it)
    and JAX's ``jax_num_cpu_devices`` option, which takes precedence over the flag in this
    process. Both only act when the backend starts, so call this at the program's entry, before
    anything creates an array or asks for devices. If the backend has started already with a
    different number of CPU devices, raises RuntimeError and changes nothing; with the same
    number it is a no-op apart from the flag.
    """
    if isinstance(n, bool) or not isinstance(n, int | np.integer) or n < 1:
        raise ValueError(f"use_host_devices: n must be a whole number >= 1 (got {n!r})")
    n = int(n)
    started = _backends_initialised()
    if started:
        have = host_device_count()
        if have != n:
            raise RuntimeError(
                f"use_host_devices({n}): JAX's backend has already started with {have} CPU "
                f"device(s); call use_host_devices before the first JAX array, jax.devices() "
                f"or jitted call (e.g. first thing in main), or set XLA_FLAGS={_FLAG}={n} "
                f"before starting Python")
        _set_xla_flag(n)
        return n
    try:
        jax.config.update("jax_num_cpu_devices", n)
    except AttributeError:  # pragma: no cover - older JAX: the XLA flag alone
        pass
    except RuntimeError as e:  # pragma: no cover - started between the check and here
        if host_device_count() != n:
            raise RuntimeError(f"use_host_devices({n}): JAX's backend has already started "
                               f"with {host_device_count()} CPU device(s)") from e
    _set_xla_flag(n)
    return n


def _resolve_devices(devices) -> tuple:
    if devices is None:
        return tuple(jax.devices())
    if isinstance(devices, int | np.integer) and not isinstance(devices, bool):
        avail = jax.devices()
        if not 1 <= devices <= len(avail):
            raise ValueError(f"map_batch: devices={devices} but {len(avail)} device(s) exist "
                             f"(use_host_devices sets the CPU device count)")
        return tuple(avail[: int(devices)])
    if isinstance(devices, str | bytes) or not isinstance(devices, Sequence):
        raise ValueError(f"devices: expected None, a number of devices or a list of JAX devices "
                         f"(got {devices!r})")
    devs = tuple(devices)
    if not devs:
        raise ValueError("map_batch: devices is empty")
    if not all(isinstance(d, jax.Device) for d in devs):
        raise ValueError(f"devices: expected JAX devices, as jax.devices() gives (got {devs!r})")
    return devs


def chunk_plan(B: int, n_devices: int, chunk: int | None) -> tuple[int, int]:
    """(c, k): items per vmapped chunk and chunks per device for a batch of B items.

    The padded batch is n_devices * k * c >= B items; c <= chunk (chunk None: one chunk per
    device, c = ceil(B / n_devices)).
    """
    per = math.ceil(B / n_devices)
    if chunk is None or chunk >= per:
        return per, 1
    k = math.ceil(per / chunk)
    return math.ceil(per / k), k


@functools.lru_cache(maxsize=128)
def _program(fn: Callable, chunk: int | None, devices: tuple, with_shared: bool,
             elemental: bool):
    """The jitted program for one (fn, chunk, devices, code generator); jit adds its own
    per-shape cache."""
    n = len(devices)

    def local(shared, xs, c):
        g = (lambda x: fn(shared, x)) if with_shared else fn
        # chunks of one run unbatched: `lax.map` with a batch size vmaps even one item, and a
        # vmapped while loop (Level 2's rounds and bisections) costs more than a plain one
        return jax.lax.map(g, xs, batch_size=c if c > 1 else None)

    def run(shared, xs):
        B = jax.tree_util.tree_leaves(xs)[0].shape[0]
        c, k = chunk_plan(B, n, chunk)
        pad = n * k * c - B
        if pad:
            xs = jax.tree_util.tree_map(
                lambda a: jnp.concatenate([a, jnp.repeat(a[-1:], pad, axis=0)]), xs)
        if n == 1:
            out = local(shared, xs, c)
        else:
            mesh = Mesh(np.asarray(devices), (AXIS,))
            out = jax.shard_map(functools.partial(local, c=c), mesh=mesh,
                                in_specs=(PartitionSpec(), PartitionSpec(AXIS)),
                                out_specs=PartitionSpec(AXIS), check_vma=False)(shared, xs)
        return jax.tree_util.tree_map(lambda a: a[:B], out)

    return jit(run, elemental=elemental)


def shortcut(check: Callable, full: Callable) -> Callable:
    """A function of one item that `check` answers cheaply where it can.

    check(*args) -> (known, value): known a bool (); where it is False the answer is
    full(*args) instead (the same arguments: arrays or pytrees of arrays; `full` returns
    `value`'s structure and dtypes, and must agree with it where known). A run of one item calls
    `full` only where needed (`lax.cond`). Under `jax.vmap` a cond on batched values would
    run both branches for every item at every call; here `full` runs, vmapped over the whole
    batch, only at calls where some item needs it (one cond on the batch), and its values are
    taken for those items. Built on `jax.custom_batching.custom_vmap`: no reverse-mode
    autodiff."""

    def one(*args):
        known, value = check(*args)
        return jax.lax.cond(known, lambda: value, lambda: full(*args))

    f = jax.custom_batching.custom_vmap(one)

    @f.def_vmap
    def rule(axis_size, in_batched, *args):
        axes = tuple(jax.tree.map(lambda b: 0 if b else None, list(in_batched)))
        known, value = jax.vmap(check, in_axes=axes, axis_size=axis_size)(*args)

        def fill():
            out = jax.vmap(full, in_axes=axes, axis_size=axis_size)(*args)
            pick = lambda v, w: jnp.where(  # noqa: E731
                jnp.reshape(known, known.shape + (1,) * (v.ndim - 1)), v, w)
            return jax.tree.map(pick, value, out)

        out = jax.lax.cond(jnp.all(known), lambda: value, fill)
        return out, jax.tree.map(lambda _: True, out)

    return f


def one_at_a_time(f: Callable, sequential: bool | None = None) -> Callable:
    """f (a function of arrays or pytrees of arrays) whose `jax.vmap` on a CPU runs the batch's
    items one after the other, each unbatched (`lax.map`), instead of vectorised; on other
    backends (a GPU) it is vectorised as usual. For a stage of a batched kernel whose loops and
    conds cost more vectorised than its arithmetic gains on a CPU (a vmapped `lax.cond` runs
    both branches, a vmapped while loop runs until its last item ends) while the rest of the
    kernel gains from the batch (the plant's steps, dispatch-bound alone). The values are f's
    on each item. sequential: True / False forces one form (None: one at a time where JAX's
    default backend is the CPU, decided when the batch is traced). Built on
    `jax.custom_batching.custom_vmap`: no reverse-mode autodiff."""
    g = jax.custom_batching.custom_vmap(f)

    @g.def_vmap
    def rule(axis_size, in_batched, *args):
        if not (jax.default_backend() == "cpu" if sequential is None else sequential):
            axes = tuple(jax.tree.map(lambda b: 0 if b else None, list(in_batched)))
            out = jax.vmap(f, in_axes=axes, axis_size=axis_size)(*args)
            return out, jax.tree.map(lambda _: True, out)
        leaves, tree = jax.tree.flatten(list(args))
        flags = jax.tree.leaves(list(in_batched))
        assert len(flags) == len(leaves), "in_batched matches the arguments"

        def item(xs):  # the batched leaves of one item, the others as they are
            it = iter(xs)
            return g(*jax.tree.unflatten(tree, [next(it) if b else a
                                               for a, b in zip(leaves, flags, strict=True)]))

        xs = [a for a, b in zip(leaves, flags, strict=True) if b]
        out = jax.lax.map(item, xs)
        return out, jax.tree.map(lambda _: True, out)

    return g


def _check_batch(args, who: str = "map_batch", error: type = ValueError) -> int:
    """B, the leading size every leaf of `args` shares (B >= 1); else `error` naming `who` and
    the first leaf that breaks it (map_batch's batch, simulate_batch's vehicles)."""
    leaves, _ = jax.tree_util.tree_flatten_with_path(args)
    if not leaves:
        raise error(f"{who}: args has no array leaves")
    first = B = None
    for path, leaf in leaves:
        shape = np.shape(leaf)
        name = jax.tree_util.keystr(path).lstrip(".") or "args"
        if len(shape) == 0:
            raise error(f"{who}: {name} has shape () (a scalar), where every leaf needs a leading "
                        f"batch axis (pass per-batch constants as shared)")
        if B is None:
            first, B = name, shape[0]
        elif shape[0] != B:
            raise error(f"{who}: {name} has shape {shape}, where every leaf has the batch's "
                        f"leading size {B} ({first}'s): different leading sizes")
    if B < 1:
        raise error(f"{who}: an empty batch (leading size 0)")
    return B


def map_batch(fn: Callable, args: Any, *, shared: Any = None, chunk: int | None = None,
              devices: int | Sequence | None = None, elemental: bool = True) -> Any:
    """Apply `fn` to every item of a batch, split over devices in chunks of at most `chunk`.

    fn: a pure function of ONE item, ``fn(item)``, or ``fn(shared, item)`` when `shared` is
    given; it must be jit-compatible and return a pytree of arrays.
    args: pytree whose leaves all have the same leading batch axis B: leaf (B, ...) -> the
    item's leaf (...).
    shared: pytree passed unchanged to every item (replicated to every device), or None.
    chunk: at most this many items are vmapped at once on a device (bounds working memory);
    None vmaps each device's whole share at once.
    devices: None (all devices of the default backend), a count (the first n), or a sequence
    of devices.
    elemental: compile with XLA's elemental CPU emitters (`xla.jit`; False: XLA's defaults).
    Returns fn's output pytree with a leading axis B on every leaf: out[i] = fn(args[i]).
    Repeated calls with the same fn object, chunk, devices and argument shapes reuse one
    compilation.
    """
    if chunk is not None and (isinstance(chunk, bool) or not isinstance(chunk, int | np.integer)
                              or chunk < 1):
        raise ValueError(f"map_batch: chunk must be a whole number >= 1 or None (got {chunk!r})")
    _check_batch(args)
    devs = _resolve_devices(devices)
    prog = _program(fn, None if chunk is None else int(chunk), devs, shared is not None,
                    bool(elemental))
    if len(devs) == 1 and devices is not None:
        args, shared = jax.device_put((args, shared), devs[0])
    return prog(shared if shared is not None else (), args)
