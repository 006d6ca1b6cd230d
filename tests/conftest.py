"""Tests run in float64 (sweeps run float32 by default); matplotlib without a display."""

import os

os.environ.setdefault("MPLBACKEND", "Agg")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

from hypothesis import settings  # noqa: E402

settings.register_profile("jaxems", max_examples=40, deadline=None, derandomize=True)
settings.load_profile("jaxems")
