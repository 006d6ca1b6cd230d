"""benchmarks/bench_sweep.py: its --option parsing (the measurements themselves are benchmarks)."""

import pytest
from repo_scripts import ROOT, load_script

bs = load_script("benchmarks/bench_sweep.py")


def test_options_are_toml_values_checked_as_a_sweep_files():
    opts = bs.parse_options(["sustain=false", "n_iter = 3", "tau_E=30.5", "soc_ref=0.4"],
                            ["baseline", "multilevel"])
    assert opts == {"sustain": False, "n_iter": 3, "tau_E": 30.5, "soc_ref": 0.4}
    assert bs.parse_options([], ["baseline"]) == {}


def test_an_option_no_measured_strategy_reads_is_refused():
    # n_iter is multilevel's: measuring the A-ECMS alone with it would time what it ignores
    with pytest.raises(SystemExit, match="n_iter: not an option of baseline") as e:
        bs.parse_options(["n_iter=3"], ["baseline"])
    assert "bench_sweep" in str(e.value)
    assert bs.parse_options(["n_iter=3"], ["baseline", "multilevel"]) == {"n_iter": 3}


@pytest.mark.parametrize("pair, says", [
    ("bogus=1", "unknown option 'bogus'"),
    ("n_iter=0", "n_iter"),
    ("sustain", "expected NAME=VALUE"),
    ("=3", "expected NAME=VALUE"),
    ("kp=fast", r"--option kp: not a valid value \('fast'"),
])
def test_a_bad_option_is_named(pair, says):
    with pytest.raises(SystemExit, match=says) as e:
        bs.parse_options([pair], ["multilevel"])
    assert "bench_sweep" in str(e.value)


def test_source_hash_names_the_files_and_their_bytes(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    for d in (a, b):
        (d / "sub" / "__pycache__").mkdir(parents=True)
        (d / "x.py").write_text("x = 1\n")
        (d / "sub" / "y.py").write_text("y = 2\n")
    (b / "sub" / "__pycache__" / "y.cpython-311.pyc").write_bytes(b"cache")
    h = bs.source_hash(a)
    assert len(h) == 12 and h == bs.source_hash(b)  # caches left out
    (b / "x.py").write_text("x = 2\n")
    assert bs.source_hash(b) != h  # a byte changed
    (b / "x.py").write_text("x = 1\n")
    (b / "sub" / "y.py").rename(b / "y.py")
    assert bs.source_hash(b) != h  # the same bytes under another path
    assert bs.code_version()["jaxems_sha256"] == bs.source_hash(ROOT / "jaxems")


cf = load_script("benchmarks/compare_fuel.py")


def test_compare_fuel_matches_a_plain_computation(tmp_path):
    import json

    import numpy as np

    rng = np.random.default_rng(1)
    b = rng.uniform(1e8, 1e9, 64)
    a = np.tile(b, 2) * (1 + rng.normal(0, 1e-4, 128))  # a batch of 128: the grid twice
    a[3] = b[3]  # one configuration exact
    pa, pb = tmp_path / "a.json", tmp_path / "b.json"
    pa.write_text(json.dumps({"strategies": {"multilevel": {"fuel_J": a.tolist()}}}))
    pb.write_text(json.dumps({"strategies": {"multilevel": {"fuel_J": b.tolist()},
                                             "baseline": {"fuel_J": b.tolist()}}}))
    r = cf.compare(cf.fuel(str(pa))["multilevel"], cf.fuel(str(pb))["multilevel"])
    rel = [abs(a[i] - b[i]) / b[i] for i in range(64)]
    assert r["n"] == 64 and r["max"] == max(rel) and r["median"] == float(np.median(rel))
    assert r["within_1e-9"] == sum(x <= 1e-9 for x in rel) >= 1
    spread = max((max(a[i], a[i + 64]) - min(a[i], a[i + 64])) / ((a[i] + a[i + 64]) / 2)
                 for i in range(64))
    assert abs(r["max_spread_same_config_A"] - spread) < 1e-12
    assert cf.main([str(pa), str(pb)]) == 0  # strategies in both files only
    pb.write_text(json.dumps({"strategies": {"multilevel": {"configs_per_s": 1.0}}}))
    with pytest.raises(SystemExit, match="no fuel_J"):
        cf.fuel(str(pb))
