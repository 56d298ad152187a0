#!/usr/bin/env bash
# Everything that needs a CUDA GPU, in one go (a lent GPU machine is held for minutes, not hours):
# build the CUDA kernels, run the `gpu` tests, read the compiler's resource report, time the
# kernels and the render step (experiments/benchmarks/bench_gpu.py) and make the paper's runtime table's CUDA
# column (experiments/benchmarks/runtime_table.py); time whole jobs on the GPU (job: dss-denoise at
# 20K and 100K points; deform: dss-deform's three scenes; train: a short dss-train on pairs rendered
# on the fly; experiments/benchmarks/gpu_stages.py). Run from the repository root on the GPU machine:
#
#     OUT=/tmp/gpu bash experiments/benchmarks/gpu_check.sh            # the default stages
#     OUT=/tmp/gpu bash experiments/benchmarks/gpu_check.sh tests      # one stage: env, tests, ptxas, rates, bench, table,
#                                                           # memcheck, racecheck (compute-sanitizer), job, deform, train
#     DEADLINE_S=540 OUT=/tmp/gpu bash experiments/benchmarks/gpu_check.sh env tests job deform train bench
#     TOY=1 DEVICE=cpu OUT=/tmp/t bash experiments/benchmarks/gpu_check.sh job deform train   # the CPU test's toy size
#
# job, deform and train run the Hydra apps: they need hydra-core, omegaconf and
# antlr4-python3-runtime (carry their wheels to a GPU machine that lacks them), deform the
# targets in $DSS_DATA (default ../shared/data) and train a dss-prep output=clouds dataset in
# $DSS_TRAIN_CLOUDS (made with open3d on a CPU machine; docs/development.md "GPU check").
# DEVICE (default cuda) is where they run; TOY=1 shrinks them to seconds; TRAIN_S (default 60) is
# the training time. Each gets its stage limit as STAGE_DEADLINE_S (5 s less), stops starting
# runs when its share of it is spent and still writes its JSON.
#
# DEADLINE_S: seconds for all the stages together (a lent machine runs one command for at most
# 10 minutes). Each stage's own limit is cut to what is left of it, less 15 s for the outputs to
# be written; a stage with less than 30 s left is skipped (and counts as failed), so the stages
# that ran still leave their files in $OUT. Put the stages that matter most first.
#
# Needs python3 with torch (CUDA build), pytest, numpy, scipy, tqdm; nvcc and ninja. No open3d:
# set DSS_BENCH_CLOUDS to a folder of clouds sampled on a machine that has it (see
# experiments/benchmarks/bench_render.py benchmark_cloud) to time the same kangaroo clouds as the CPU tables.
# Each stage's output goes to $OUT/<stage>.txt; the JSONs to $OUT. A failing stage does not stop
# the later ones; the exit status is the number of failed stages. The default stages write 10 files
# and memcheck and racecheck 2 more; where a tool returns only a few files from the GPU machine,
# write to a scratch OUT and pack it, e.g.
#     OUT=/tmp/g bash experiments/benchmarks/gpu_check.sh ...; tar -C /tmp/g -cf "$RETURNED/gpu.tar" .
set -uo pipefail
OUT=${OUT:-results/gpu}
mkdir -p "$OUT"
export PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH} PYTHONUNBUFFERED=1
export TORCH_EXTENSIONS_DIR=${TORCH_EXTENSIONS_DIR:-/tmp/dss_torch_extensions}
export MAX_JOBS=${MAX_JOBS:-$(nproc)}
PY=${PYTHON:-python3}
STAGES=${*:-env tests ptxas rates bench table}
DEVICE=${DEVICE:-cuda}
TOY_ARG=()
[ "${TOY:-0}" = 1 ] && TOY_ARG=(--toy)
DEADLINE_S=${DEADLINE_S:-}
started=$(date +%s)
failed=0

stage() {  # stage NAME SECONDS CMD...: run with a time limit, log to $OUT/NAME.txt
  local name=$1 limit=$2
  shift 2
  if [ -n "$DEADLINE_S" ]; then
    local left=$((DEADLINE_S - ($(date +%s) - started) - 15))
    if [ "$left" -lt 30 ]; then
      echo "!!! $name skipped: ${left} s left of DEADLINE_S=$DEADLINE_S" | tee "$OUT/$name.txt"
      failed=$((failed + 1))
      return
    fi
    [ "$left" -lt "$limit" ] && limit=$left
  fi
  echo "=== $name ($(date -u +%H:%M:%S), at most ${limit} s)"
  STAGE_DEADLINE_S=$((limit - 5)) timeout "$limit" "$@" >"$OUT/$name.txt" 2>&1
  local rc=$?
  if [ $rc -ne 0 ]; then
    echo "!!! $name failed (exit $rc)"
    failed=$((failed + 1))
  fi
  tail -n "${TAIL:-15}" "$OUT/$name.txt"
}

for s in $STAGES; do
  case $s in
  env)
    stage env 60 bash -c "nvidia-smi; $PY -V; nvcc --version; $PY -c 'import torch; print(torch.__version__, torch.version.cuda, torch.cuda.get_device_name(0))'"
    ;;
  tests)  # builds both modules (CPU kernel for the comparisons), then every gpu-marked test
    stage tests 420 "$PY" -m pytest -p no:cacheprovider -q -m gpu -ra tests/test_cuda_build.py tests/test_render_cuda.py tests/test_render_backward.py tests/test_knn.py
    ;;
  memcheck)  # the kernel tests under compute-sanitizer (out-of-bounds and misaligned accesses); run after tests (built).
    # Without torch's caching allocator every tensor is its own allocation, so an access past a
    # tensor's end is caught even where the cache would have put another tensor there.
    stage memcheck 240 env PYTORCH_NO_CUDA_MEMORY_CACHING=1 compute-sanitizer --tool memcheck --error-exitcode 9 \
      "$PY" -m pytest -p no:cacheprovider -q -m gpu \
      tests/test_cuda_build.py -k "not denoising_sized"
    ;;
  racecheck)  # shared-memory hazards of the tiled kernels, on the scenes with multi-batch bins and depth ties
    stage racecheck 240 compute-sanitizer --tool racecheck --error-exitcode 9 "$PY" -m pytest -p no:cacheprovider -q -m gpu \
      tests/test_cuda_build.py -k "deep_bins or ties"
    ;;
  ptxas)  # registers, shared memory, spills of every kernel for this GPU
    stage ptxas 180 bash -c 'for f in dss/csrc/*_cuda.cu; do nvcc -c -std=c++17 -O3 --fmad=false -arch=native -Xptxas -v \
      -I dss/csrc "$f" -o /tmp/dss_cuda_ptxas.o || exit 1; done'
    ;;
  bench)
    stage bench 300 "$PY" -m experiments.benchmarks.bench_gpu --points 20000 100000 --repeats 20 --profile --out "$OUT/bench_gpu.json"
    ;;
  rates)  # the GPU's own ceilings (FP32 matmul, device copy) and the counted workloads' floors on them
    rm -f "$OUT/gpu_rates.json"  # never let the table stage read an earlier run's rates
    stage rates 120 "$PY" -m experiments.benchmarks.perf_counts --gpu-rates "$OUT/gpu_rates.json"
    ;;
  table)  # after rates, its floors use the GPU's measured rates (else the H100's published spec)
    rates_arg=()
    [ -f "$OUT/gpu_rates.json" ] && rates_arg=(--gpu-rates "$OUT/gpu_rates.json")
    # (the ${a[@]+...} form: bash < 4.4 calls an empty array unbound under set -u)
    stage table 420 "$PY" -m experiments.benchmarks.runtime_table --backends cuda --no-progress --out "$OUT/runtime_table_cuda" \
      ${rates_arg[@]+"${rates_arg[@]}"}
    ;;
  job)  # dss-denoise on the example (20K) and on 100K samples of its mesh: whole-job wall time, per-stage profile
    stage job 120 "$PY" -m experiments.benchmarks.gpu_stages job --device "$DEVICE" --out "$OUT/job" ${TOY_ARG[@]+"${TOY_ARG[@]}"}
    ;;
  deform)  # dss-deform sphere_teapot, sphere_bunny, cube_yoga (default preset): accuracy and time
    stage deform 100 "$PY" -m experiments.benchmarks.gpu_stages deform --device "$DEVICE" --out "$OUT/deform" \
      ${TOY_ARG[@]+"${TOY_ARG[@]}"}
    ;;
  train)  # a small planes model on pairs rendered on the fly: metrics.json and denoiser.onnx
    stage train 100 "$PY" -m experiments.benchmarks.gpu_stages train --device "$DEVICE" --seconds "${TRAIN_S:-60}" \
      --out "$OUT/train" ${TOY_ARG[@]+"${TOY_ARG[@]}"}
    ;;
  *)
    echo "unknown stage $s (env, tests, ptxas, rates, bench, table, memcheck, racecheck, job, deform, train)"
    failed=$((failed + 1))
    ;;
  esac
done
exit $failed
