"""A script of the repository (experiments/, benchmarks/) loaded as a module, for its tests."""

import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def load_script(rel: str, name: str | None = None):
    """The module of the script at ROOT / rel (name: its module name, default the file's)."""
    path = ROOT / rel
    spec = importlib.util.spec_from_file_location(name or path.stem, path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod
