# Two commands set up and run everything on a fresh machine with Python >= 3.11 and pip:
#   make demo    the main job on the bundled data (writes out/)
#   make test    the whole test suite
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.jaxems-installed

.PHONY: demo test test-random bench clean

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[test]'
	touch $(STAMP)

demo: $(STAMP)
	@$(PY) -m jaxems.demo --out out

# --dist loadfile: each test module on one worker, so that a module's shared fixture (every
# strategy on the short track, the sweep) is computed once (loadgroup did not group here);
# --no-loadscope-reorder: modules in the order tests/conftest.py gives (longest compilations
# first, the modules that reuse test_strategies' compilations from the shared cache last)
test: $(STAMP)
	$(PY) -m pytest -n 2 --dist loadfile --no-loadscope-reorder -p no:cacheprovider

# the property tests (hypothesis) with new random examples, not the fixed set `make test`
# replays: from time to time, to find what that set never draws; SEED=N replays a run
test-random: $(STAMP)
	$(PY) -m pytest -n 2 --dist loadfile -p no:cacheprovider -m hypothesis \
		--hypothesis-profile=random $(if $(SEED),--hypothesis-seed=$(SEED))

bench: $(STAMP)
	$(PY) benchmarks/bench_level1.py

clean:
	rm -rf out .pytest_cache .hypothesis
