#!/usr/bin/env bash
# The GPU figures of the README's "On a GPU", phase by phase (each fits one 10-minute call of a
# lent GPU machine; no install: its python3 has JAX with CUDA, numpy, optax, pandas, pyarrow,
# pytest and hypothesis).
#   bash benchmarks/gpu.sh PHASE [OUT]
#   PHASE: info | lease | throughput | multilevel | determinism | mpc | batch | float64 | tests
#          | suite
# With a lease of 15 device minutes: `lease` (about 6 minutes on an H200), then `suite` (about
# 5 minutes) at once on the same warm machine (a start takes 1-2 minutes).
# JSON files go to OUT (default $OUT, else out/gpu); progress lines on stderr. Compare a run's
# fuel with a CPU run's: python benchmarks/compare_fuel.py GPU.json CPU.json
set -u
phase=${1:?phase}
out=${2:-${OUT:-out/gpu}}
mkdir -p "$out"
export PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH} PYTHONUNBUFFERED=1
B="python3 benchmarks/bench_sweep.py --devices 1 --json"
# one bench_sweep run into $out/FILE: TIMEOUT FILE BATCH CHUNK STRATEGIES REPEATS [ARGS...]
sweep() {
  local t=$1 f=$2 b=$3 c=$4 s=$5 r=$6
  shift 6
  timeout "$t" $B --batch "$b" --chunk "$c" --strategies "$s" --repeats "$r" "$@" > "$out/$f"
}
conv_base() { sweep "$1" gpu_b1024_conv_base.json 1024 1024 conventional,baseline "$2" --keep-fuel; }
multilevel() { sweep "$1" gpu_b1024_multilevel.json 1024 1024 multilevel 2 --keep-fuel; }
case $phase in
  info)
    nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.sm,clocks.max.sm --format=csv
    python3 -c "import jax, numpy; print('jax', jax.__version__, 'numpy', numpy.__version__, jax.devices())"
    ;;
  lease)  # the README's GPU table in one call (2026-11-27 on an H200: 242 s to 4096, 8192
    # about 130 s more; run then in two calls, commands as here): the batch for
    # conventional, baseline and multilevel, then multilevel at 4096 and 8192 (79 GiB: 8192
    # needs an H200; on an 80 GB H100 the last run fails for memory)
    conv_base 150 2
    multilevel 230
    sweep 170 gpu_b4096_multilevel.json 4096 4096 multilevel 1
    sweep 150 gpu_b8192_multilevel.json 8192 8192 multilevel 1
    ;;
  throughput)  # the batch, one vmap of the whole batch (the MPC: phase mpc)
    conv_base 240 3
    multilevel 330
    ;;
  multilevel)  # the throughput phase's multilevel run alone
    multilevel 330
    ;;
  determinism)  # the same with XLA's deterministic GPU ops (scatter-adds in a fixed order):
    # does a configuration's result still depend on its place in the batch? (compare_fuel.py)
    export XLA_FLAGS="--xla_gpu_deterministic_ops=true${XLA_FLAGS:+ $XLA_FLAGS}"
    sweep 330 gpu_b1024_multilevel_deterministic.json 1024 1024 multilevel 2 --keep-fuel
    ;;
  mpc)  # LongHaul's batch of 1024 did not finish its compilation and first call in 400 s
    sweep 290 gpu_regional_b256_mpc.json 256 256 multilevel-mpc 1 --route RegionalDelivery \
      --keep-fuel
    ;;
  batch)  # multilevel's time against the batch (and the chunk)
    sweep 130 gpu_b256_multilevel.json 256 256 multilevel 1
    sweep 330 gpu_b2048_multilevel.json 2048 1024 multilevel 1
    sweep 210 gpu_b4096_multilevel.json 4096 4096 multilevel 1
    ;;
  float64)  # to compare with the CPU's float64 (same batch, same chunk)
    sweep 120 gpu_b64_multilevel_f64.json 64 64 multilevel 1 --precision float64 --keep-fuel
    ;;
  tests)  # the kernels' tests against their references, on the GPU
    set -o pipefail
    XLA_PYTHON_CLIENT_PREALLOCATE=false timeout 250 python3 -m pytest -x -p no:cacheprovider \
      tests/test_dp.py tests/test_level1.py tests/test_guards.py tests/test_powersplit.py \
      tests/test_plant.py tests/test_velocity.py tests/test_shard.py 2>&1 | tee "$out/gpu_tests.log" \
      | tail -15
    ;;
  suite)  # the whole suite on the GPU in 8 processes (about 5 minutes on an H100 or H200;
    # no -q: pyproject.toml's addopts has one, and a second drops the closing count line)
    set -o pipefail
    XLA_PYTHON_CLIENT_PREALLOCATE=false timeout 560 python3 -m pytest -n 8 \
      -p no:cacheprovider tests 2>&1 | tee "$out/gpu_suite.log" | tail -30
    ;;
  *) echo "gpu.sh: unknown phase $phase" >&2; exit 2 ;;
esac
