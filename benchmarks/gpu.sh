#!/usr/bin/env bash
# The checks and figures of a session that is lent a GPU machine, as one command there (the lease is short: about
# 15 minutes of device time in all, machine start included). From the repository root:
#
#   bash benchmarks/gpu.sh                                        # on the GPU machine; results in $OUT
#   ARCH=cpu QUICK=1 WHEELS= OUT=/tmp/gpu bash benchmarks/gpu.sh  # a dry run of the script on a CPU
#
# Python packages the machine lacks (Taichi, for one) travel as wheels in $WHEELS (default .whl/; see the device
# tool's notes) and are installed into /tmp/site. BUDGET (seconds, default 540) bounds the whole script: each step
# gets at most what is left, and the steps run in order of importance.
#
# 1. At once (each compile uses one CPU core, and the machine has many), for at most 240 s: every `bench gradient`
#    case and the larger GPU cases compiled into Taichi's offline cache (benchmarks/gpu_cases.py compile),
#    tests/test_gpu.py (the tiny scene on CUDA against the CPU, `mls-mpm check` in 2D; the 3D check in a process of
#    its own), and the first runs of the README's 2D and 3D scenes (compile included).
# 2. One after another on a quiet GPU: `mls-mpm bench gradient --arch gpu`, 2D then 3D (gpu_gradient_2d.md,
#    gpu_gradient_3d.md), the larger cases in random and cell order, then Taichi's kernel profile of the 3D one
#    (gpu_scale.md), the two scenes again with the cache warm (scenes.txt).
#
# It writes 8 files into $OUT, the most the device tool brings back: tee nothing else there. On an H200 with 16 CPU
# cores (2026-12-04 17:26 UTC) it took 510 s (phase 1 about 210 s), plus about 30 s to start the machine and copy the tree
# (Taichi's wheel is 56 MB of the 64 MiB that travels; imageio-ffmpeg's 68 MB cannot come along, so no MP4 there).
set -u
OUT=${OUT:-renders/gpu}
ARCH=${ARCH:-gpu}
PY=${PYTHON:-python3}
QUICK=${QUICK:-}
BUDGET=${BUDGET:-540}
START=$(date +%s)
rm -rf /tmp/gpu_runs
mkdir -p "$OUT" /tmp/gpu_runs
export PYTHONUNBUFFERED=1 TI_LOG_LEVEL=error
WHEELS=${WHEELS-.whl}  # WHEELS= (empty): install nothing
if [ -n "$WHEELS" ] && ls "$WHEELS"/*.whl >/dev/null 2>&1; then
    "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site "$WHEELS"/*.whl \
        || { echo "gpu.sh: installing $WHEELS/*.whl failed"; exit 1; }
    export PYTHONPATH=/tmp/site
fi
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"

left() { echo $((BUDGET - ($(date +%s) - START))); }
# step SECONDS LOG CMD...: run CMD for at most SECONDS (and what the budget has left), its output appended to LOG
step() {
    local want=$1 log=$2; shift 2
    local t; t=$(left); [ "$want" -lt "$t" ] && t=$want
    if [ "$t" -le 5 ]; then echo "skipped (budget spent): $*" >>"$log"; return 124; fi
    echo "\$ $* (at most ${t} s)" >>"$log"
    local t0; t0=$(date +%s%N)
    timeout -s TERM -k 10 "$t" "$@" >>"$log" 2>&1
    local rc=$?
    echo "exit $rc after $(( ($(date +%s%N) - t0) / 1000000 )) ms" >>"$log"
    return $rc
}
MLS=("$PY" -m mls_mpm.cli)
Q=${QUICK:+--quick}
if [ -n "$QUICK" ]; then  # the dry run: short scenes, the 2D benchmark only
    SCENE2D=(--set optimize.iterations=2); SCENE3D=(--set sim.steps=20 --set control.stride=10 --set optimize.iterations=2)
else
    SCENE2D=(); SCENE3D=()
fi

{
    date -u
    nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.sm,clocks.max.sm --format=csv 2>&1
    grep -m1 "model name" /proc/cpuinfo; nproc
    "$PY" -c "import sys, taichi, numpy; print(sys.version.split()[0], 'taichi', taichi.__version__, 'numpy', numpy.__version__)" 2>&1 | tail -1
    "$PY" -c "from mls_mpm.bench import backend_here; print('backend', backend_here('$ARCH'))" 2>&1 | tail -1
} >"$OUT/machine.txt"
cat "$OUT/machine.txt"
grep -q "^backend " "$OUT/machine.txt" || { echo "gpu.sh: sim.arch = $ARCH does not start here; stopping"; exit 1; }

echo "== phase 1 (at once): compile, tests, first scene runs"
step 240 "$OUT/compile.txt" "$PY" benchmarks/gpu_cases.py compile --arch "$ARCH" $Q &
step 240 "$OUT/tests.txt" "$PY" -m pytest -q -p no:cacheprovider -n 0 -rs tests/test_gpu.py -k "not 3d" &
step 240 /tmp/gpu_runs/t3d.txt "$PY" -m pytest -q -p no:cacheprovider -n 0 -rs tests/test_gpu.py -k 3d &
# render.mp4 = false: imageio-ffmpeg's wheel (68 MB) does not travel beside Taichi's; the frames still render
step 240 /tmp/gpu_runs/s2d_cold.txt "${MLS[@]}" run scenes/circle_to_torus.toml --arch "$ARCH" \
    --out /tmp/gpu_runs/s2d_cold --set render.mp4=false "${SCENE2D[@]}" &
step 240 /tmp/gpu_runs/s3d_cold.txt "${MLS[@]}" run scenes/sphere_to_torus_3d.toml --arch "$ARCH" --no-render \
    --out /tmp/gpu_runs/s3d_cold "${SCENE3D[@]}" &
wait
cat /tmp/gpu_runs/t3d.txt >>"$OUT/tests.txt"
cat /tmp/gpu_runs/s2d_cold.txt /tmp/gpu_runs/s3d_cold.txt >"$OUT/scenes.txt"
grep -E "passed|failed|error" "$OUT/tests.txt"; cat "$OUT/compile.txt"

echo "== phase 2 (one after another): timings"
step 90 "$OUT/bench.txt" "${MLS[@]}" bench gradient --arch "$ARCH" --dim 2 --repeats 2 --out "$OUT/gpu_gradient_2d.md" $Q
[ -z "$QUICK" ] && step 150 "$OUT/bench.txt" "${MLS[@]}" bench gradient --arch "$ARCH" --dim 3 --repeats 2 \
    --out "$OUT/gpu_gradient_3d.md"
step 120 "$OUT/gpu_scale.md" "$PY" benchmarks/gpu_cases.py scale --arch "$ARCH" $Q
step 60 "$OUT/gpu_scale.md" "$PY" benchmarks/gpu_cases.py profile --arch "$ARCH" $Q
step 60 "$OUT/scenes.txt" "${MLS[@]}" run scenes/circle_to_torus.toml --arch "$ARCH" --no-render \
    --out /tmp/gpu_runs/s2d_warm "${SCENE2D[@]}"
[ -f /tmp/gpu_runs/s3d_cold/summary.json ] && step 90 "$OUT/scenes.txt" "${MLS[@]}" run scenes/sphere_to_torus_3d.toml \
    --arch "$ARCH" --no-render --out /tmp/gpu_runs/s3d_warm "${SCENE3D[@]}"
for d in /tmp/gpu_runs/*/; do
    [ -f "$d/summary.json" ] && "$PY" -c "import json, sys; s = json.load(open(sys.argv[1] + 'summary.json')); \
print(sys.argv[1], s['backend'], 'loss', s['loss_initial'], '->', s['loss_final'], 'iou', s['iou'] and round(s['iou'], 3), \
'wall', round(s['wall_seconds'], 1), 's')" "$d"
done >>"$OUT/scenes.txt"
cat "$OUT"/gpu_gradient_*.md "$OUT/gpu_scale.md" 2>/dev/null; tail -4 "$OUT/scenes.txt"
echo "gpu.sh: done in $(( $(date +%s) - START )) s"
