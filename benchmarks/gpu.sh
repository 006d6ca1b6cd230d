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
case $phase in
  info)
    nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.sm,clocks.max.sm --format=csv
    python3 -c "import jax, numpy; print('jax', jax.__version__, 'numpy', numpy.__version__, jax.devices())"
    ;;
  lease)  # the README's GPU table in one call (2026-11-27 on an H200: 242 s to 4096, 8192
    # about 130 s more; run then in two calls, commands as here): the issue's
    # batch for conventional, baseline and multilevel, then multilevel at 4096 and 8192 (79 GiB:
    # 8192 needs an H200; on an 80 GB H100 the last run fails for memory)
    timeout 150 $B --batch 1024 --chunk 1024 --strategies conventional,baseline --repeats 2 \
      --keep-fuel > "$out/gpu_b1024_conv_base.json"
    timeout 230 $B --batch 1024 --chunk 1024 --strategies multilevel --repeats 2 \
      --keep-fuel > "$out/gpu_b1024_multilevel.json"
    timeout 170 $B --batch 4096 --chunk 4096 --strategies multilevel --repeats 1 \
      > "$out/gpu_b4096_multilevel.json"
    timeout 150 $B --batch 8192 --chunk 8192 --strategies multilevel --repeats 1 \
      > "$out/gpu_b8192_multilevel.json"
    ;;
  throughput)  # the batch, one vmap of the whole batch (the MPC: phase mpc)
    timeout 240 $B --batch 1024 --chunk 1024 --strategies conventional,baseline --repeats 3 \
      --keep-fuel > "$out/gpu_b1024_conv_base.json"
    timeout 330 $B --batch 1024 --chunk 1024 --strategies multilevel --repeats 2 \
      --keep-fuel > "$out/gpu_b1024_multilevel.json"
    ;;
  multilevel)  # the throughput phase's multilevel run alone
    timeout 330 $B --batch 1024 --chunk 1024 --strategies multilevel --repeats 2 \
      --keep-fuel > "$out/gpu_b1024_multilevel.json"
    ;;
  determinism)  # the same with XLA's deterministic GPU ops (scatter-adds in a fixed order):
    # does a configuration's result still depend on its place in the batch? (compare_fuel.py)
    XLA_FLAGS="--xla_gpu_deterministic_ops=true${XLA_FLAGS:+ $XLA_FLAGS}" timeout 330 $B \
      --batch 1024 --chunk 1024 --strategies multilevel --repeats 2 --keep-fuel \
      > "$out/gpu_b1024_multilevel_deterministic.json"
    ;;
  mpc)  # LongHaul's batch of 1024 did not finish its compilation and first call in 400 s
    timeout 290 $B --route RegionalDelivery --batch 256 --chunk 256 --strategies multilevel-mpc \
      --repeats 1 --keep-fuel > "$out/gpu_regional_b256_mpc.json"
    ;;
  batch)  # multilevel's time against the batch (and the chunk)
    timeout 130 $B --strategies multilevel --repeats 1 --batch 256 --chunk 256 \
      > "$out/gpu_b256_multilevel.json"
    timeout 330 $B --strategies multilevel --repeats 1 --batch 2048 --chunk 1024 \
      > "$out/gpu_b2048_multilevel.json"
    timeout 210 $B --strategies multilevel --repeats 1 --batch 4096 --chunk 4096 \
      > "$out/gpu_b4096_multilevel.json"
    ;;
  float64)  # to compare with the CPU's float64 (same batch, same chunk)
    timeout 120 $B --strategies multilevel --repeats 1 --batch 64 --chunk 64 \
      --precision float64 --keep-fuel > "$out/gpu_b64_multilevel_f64.json"
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
