"""benchmarks/bench_sweep.py: its --option parsing (the measurements themselves are benchmarks)."""

import importlib.util
from pathlib import Path

import pytest

_PATH = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_sweep.py"
_spec = importlib.util.spec_from_file_location("bench_sweep", _PATH)
bs = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bs)


def test_options_are_toml_values_checked_as_a_sweep_files():
    opts = bs.parse_options(["sustain=false", "n_iter = 3", "tau_E=30.5", "soc_ref=0.4"])
    assert opts == {"sustain": False, "n_iter": 3, "tau_E": 30.5, "soc_ref": 0.4}
    assert bs.parse_options([]) == {}


@pytest.mark.parametrize("pair, says", [
    ("bogus=1", "unknown option 'bogus'"),
    ("n_iter=0", "n_iter"),
    ("sustain", "expected NAME=VALUE"),
    ("=3", "expected NAME=VALUE"),
    ("kp=fast", "--option 'kp=fast'"),
])
def test_a_bad_option_is_named(pair, says):
    with pytest.raises(SystemExit, match=says) as e:
        bs.parse_options([pair])
    assert "bench_sweep" in str(e.value)
