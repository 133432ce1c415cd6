#!/usr/bin/env bash
# Everything that needs a CUDA GPU (or many cores), in one command:   bash tools/gpu_check.sh [quick]
#
#   setup        (with GPU_CHECK_WHEELS=DIR) pip install --no-deps --no-index DIR/*.whl first
#   probe        the machine: GPU, driver, PCIe link, cores, package versions
#   doctor       iristac doctor --no-compile (the stack, one line per piece)
#   live         tools/gpu_live_check.py: the near-field path at 320x240 on 1, 2, 4, 8, 16 threads
#                (frames in parallel: CPUFramePipeline, and one Python task a frame for comparison),
#                the 16-core target; the GPU pipeline: upload alone, solve alone, whole from pinned,
#                from numpy and from HDF5 files read straight into its pinned buffers
#   tests        the CUDA tests (pytest: tracer, fused kernel and pipeline, HDF5 into pinned
#                buffers, the torch paths on cuda)
#   trace_cli    iristac sim trace default --device cuda at 1e6, 1e8, 1e9 rays
#   tracer       (not with "quick") compile time, CPU/GPU agreement, CPU threads (tools/gpu_trace_check.py)
#   doctor_full  (not with "quick") iristac doctor, every kernel compiled (PTX) and run on the device
#   bench_live   (not with "quick") iristac bench live --device cuda, the whole benchmark
#
# "quick" takes about 3 minutes on a 16-core H200 machine (the steps' limits add up to 600 s).
# Each step runs under its own time limit and the script goes on when one fails. Results in $OUT
# (default ./gpu-check-out): summary.txt (a line per step, exit status and seconds, then the
# headline figures, written as they come), gpu_check.log (everything), live.json. PYTHON picks the
# interpreter (default python3), GPU_BATCH the frames per upload (default 256), GPU_CHECK_STEPS a
# subset of the steps (names as above, space-separated).
set -u
ROOT=$(cd "$(dirname "$0")/.." && pwd)
cd "$ROOT"
OUT=${OUT:-gpu-check-out}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1
export PYTHONPATH="$ROOT${PYTHONPATH:+:$PYTHONPATH}"  # tools/*.py import the checkout's packages
export PY=${PYTHON:-python3}
export OUT
QUICK=${1:-}
LOG="$OUT/gpu_check.log"
SUMMARY="$OUT/summary.txt"
: > "$SUMMARY"

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
  echo "$name: exit $rc, $((SECONDS - t0)) s" | tee -a "$SUMMARY" "$LOG"
}

setup() {
  "$PY" -m pip install -q --no-deps --no-index "$GPU_CHECK_WHEELS"/*.whl
}

probe() {
  nvidia-smi --query-gpu=name,driver_version,pcie.link.gen.current,pcie.link.gen.max,pcie.link.width.current,memory.total,clocks.sm,clocks.max.sm --format=csv
  echo "cores: $(nproc)"
  lscpu | grep -E "^(Model name|Thread|Core|Socket|NUMA node\(s\)|L3)" || true
  free -g | head -2
  df -h "${TMPDIR:-/tmp}" | tail -1
  uptime
  "$PY" - <<'EOF'
import importlib.metadata as m
for d in ("numpy", "numba", "numba-cuda", "llvmlite", "torch", "scipy", "h5py", "opencv-python-headless",
          "cuda-bindings", "cuda-core", "cuda-toolkit", "nvidia-nvvm", "nvidia-nvjitlink", "triton", "cupy-cuda13x"):
    try:
        print(f"{d} {m.version(d)}")
    except m.PackageNotFoundError:
        print(f"{d} -")
import h5py
print("hdf5", h5py.version.hdf5_version)
EOF
}

live() {
  "$PY" tools/gpu_live_check.py "$OUT/live.json" "$OUT/live_summary.txt"
  local rc=$?
  [ -f "$OUT/live_summary.txt" ] && { echo "--- live figures"; cat "$OUT/live_summary.txt"; } >> "$OUT/summary.txt"
  return $rc
}

trace_cli() {
  for n in 1000000 100000000 1000000000; do
    "$PY" -m pipeline sim trace default --device cuda --rays "$n" --json > "$OUT/trace_$n.json" || return 1
    "$PY" -c "import json,sys; d=json.load(open(sys.argv[1])); print(sys.argv[2], 'rays:', round(d['rays_per_second']/1e6,1), 'M rays/s;', round(d['seconds'],3), 's; compile or load', round(d['compile_seconds'],2), 's; on screen', d['fraction_on_screen'], '; residual', d['energy_residual'], '; counters', d['counters'])" "$OUT/trace_$n.json" "$n" | tee -a "$OUT/summary.txt"
    rm -f "$OUT/trace_$n.json"
  done
}

if [ "$QUICK" = "quick" ]; then
  DEFAULT_STEPS="setup probe doctor live tests trace_cli"
else
  DEFAULT_STEPS="setup probe doctor live tests trace_cli tracer doctor_full bench_live"
fi
STEPS=${GPU_CHECK_STEPS:-$DEFAULT_STEPS}
want() { case " $STEPS " in *" $1 "*) return 0 ;; *) return 1 ;; esac; }
if want setup && [ -n "${GPU_CHECK_WHEELS:-}" ]; then
  export GPU_CHECK_WHEELS
  step setup 90 setup
fi
want probe && step probe 30 probe
want doctor && step doctor 60 "$PY" -m pipeline doctor --no-compile
want live && step live 200 live
want tests && step tests 120 "$PY" -m pytest -q -p no:cacheprovider tests/sim/test_tracer_kernel.py \
  tests/pipeline/normals/test_gpu_nearfield.py tests/pipeline/normals/test_fast_paths.py \
  tests/pipeline/stages/test_batched_stages.py -k "(cuda or gpu) and not ptx and not simulator"
want trace_cli && step trace_cli 100 trace_cli
want tracer && step tracer 240 "$PY" tools/gpu_trace_check.py "$OUT/trace.json"
want doctor_full && step doctor_full 400 "$PY" -m pipeline doctor
want bench_live && step bench_live 1800 "$PY" -m pipeline bench live --device cuda --sizes 320x240 --no-startup
echo "=== summary" | tee -a "$LOG"
cat "$SUMMARY"
