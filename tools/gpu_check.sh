#!/usr/bin/env bash
# Everything that needs a CUDA GPU, in one command:   bash tools/gpu_check.sh [quick]
#
#   1. the machine: GPU, driver, PCIe link, cores, package versions
#   2. iristac doctor --no-compile (the stack, one line per piece)
#   3. the ray tracer: compile time, CPU/GPU agreement (books, counters, images), CPU threads
#      (tools/gpu_trace_check.py), then `iristac sim trace default --device cuda` at 1e6, 1e8, 1e9 rays
#   4. the live near-field path: many cores and the GPU pipeline (tools/gpu_live_check.py)
#   5. the CUDA tests (pytest: the tracer, the fused kernel and pipeline, the torch paths on cuda)
#   6. iristac doctor with every kernel compiled (PTX) and run on the device
#   7. (not with "quick") iristac bench live --device cuda, the whole benchmark
#
# Each step runs under its own time limit and the script goes on when one fails; a summary
# line per step (exit status, seconds) ends the output. Results: $OUT (default ./gpu-check-out):
# gpu_check.log (everything), trace.json, live.json, summary.txt. Set PYTHON to choose the
# interpreter (default python3), GPU_BATCH the frames per upload (default 256) and
# GPU_CHECK_STEPS a subset of the steps (names as in the summary, space-separated).
set -u
OUT=${OUT:-gpu-check-out}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1
export PY=${PYTHON:-python3}
export OUT
QUICK=${1:-}
LOG="$OUT/gpu_check.log"
: > "$OUT/summary.txt"

step() {  # step NAME SECONDS COMMAND...
  local name=$1 limit=$2
  shift 2
  echo "=== $name (limit ${limit}s)" | tee -a "$LOG"
  local t0=$SECONDS
  if declare -F "$1" > /dev/null; then  # a function of this script: timeout runs programs only
    timeout "$limit" bash -c "$(declare -f "$1"); $*" 2>&1 | tee -a "$LOG"
  else
    timeout "$limit" "$@" 2>&1 | tee -a "$LOG"
  fi
  local rc=${PIPESTATUS[0]}
  echo "$name: exit $rc, $((SECONDS - t0)) s" | tee -a "$OUT/summary.txt" "$LOG"
}

probe() {
  nvidia-smi --query-gpu=name,driver_version,pcie.link.gen.current,pcie.link.gen.max,pcie.link.width.current,memory.total,clocks.sm,clocks.max.sm --format=csv
  echo "cores: $(nproc)"
  lscpu | grep -E "^(Model name|Thread|Core|Socket|NUMA node\(s\)|L3)" || true
  uptime
  "$PY" - <<'EOF'
import importlib.metadata as m
for d in ("numpy", "numba", "numba-cuda", "llvmlite", "torch", "cuda-bindings", "cuda-core", "cuda-toolkit",
          "nvidia-nvvm", "nvidia-cuda-nvcc", "nvidia-nvjitlink", "triton", "cupy-cuda13x"):
    try:
        print(f"{d} {m.version(d)}")
    except m.PackageNotFoundError:
        print(f"{d} -")
EOF
}

trace_cli() {
  for n in 1000000 100000000 1000000000; do
    "$PY" -m pipeline sim trace default --device cuda --rays "$n" --json > "$OUT/trace_$n.json" || return 1
    "$PY" -c "import json,sys; d=json.load(open(sys.argv[1])); print(sys.argv[2], 'rays:', round(d['rays_per_second']/1e6,1), 'M rays/s;', round(d['seconds'],3), 's; compile or load', round(d['compile_seconds'],2), 's; on screen', d['fraction_on_screen'], '; residual', d['energy_residual'], '; counters', d['counters'])" "$OUT/trace_$n.json" "$n"
    rm -f "$OUT/trace_$n.json"
  done
}

STEPS=${GPU_CHECK_STEPS:-probe doctor tracer trace_cli live tests doctor_full bench_live}
want() { case " $STEPS " in *" $1 "*) return 0 ;; *) return 1 ;; esac; }
want probe && step probe 60 probe
want doctor && step doctor 120 "$PY" -m pipeline doctor --no-compile
want tracer && step tracer 240 "$PY" tools/gpu_trace_check.py "$OUT/trace.json"
want trace_cli && step trace_cli 180 trace_cli
want live && step live 300 "$PY" tools/gpu_live_check.py "$OUT/live.json"
want tests && step tests 400 "$PY" -m pytest -q -x -p no:cacheprovider tests/sim/test_tracer_kernel.py \
  tests/pipeline/normals/test_gpu_nearfield.py tests/pipeline/normals/test_fast_paths.py \
  tests/pipeline/stages/test_batched_stages.py -k "(cuda or gpu) and not ptx and not simulator"
want doctor_full && step doctor_full 400 "$PY" -m pipeline doctor
if [ "$QUICK" != "quick" ] && want bench_live; then
  step bench_live 1800 "$PY" -m pipeline bench live --device cuda --sizes 320x240 --no-startup
fi
echo "=== summary" | tee -a "$LOG"
cat "$OUT/summary.txt"
