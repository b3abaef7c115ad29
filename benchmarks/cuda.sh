#!/usr/bin/env bash
# Issue #18's checks on one GPU, in one go (a lent GPU machine has a few minutes; this is sized to fit ten):
#   1. the package's CUDA tests (tests/test_cuda.py: the same seed gives the CPU's numbers, checkpoints move);
#   2. the rigid body's main run on the GPU (benchmarks/rigid_body.py --device cuda, infinite horizon only),
#      whose goals table then carries the "under 3 minutes on one GPU";
#   3. the LQ ladder at n = 2, 4, 8, 12, 16 on the GPU (benchmarks/dimension.py --device cuda).
# Each step has its own time limit and the next runs whatever the last did; all output goes to one log.
#
#   bash benchmarks/cuda.sh                # results under benchmarks/results/cuda_nd/
#   OUT=/some/dir bash benchmarks/cuda.sh  # or there (the device tool's $OUT)
#
# Needs python3 with torch (CUDA), numpy, scipy, tqdm, matplotlib and pytest; PYTHON= picks another interpreter.
set -uo pipefail
out=${OUT:-benchmarks/results/cuda_nd}
py=${PYTHON:-python3}
mkdir -p "$out/rigid_body" "$out/dimension"
export PYTHONUNBUFFERED=1 PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
log="$out/log.txt"
: >"$log"
step() {  # step SECONDS COMMAND...: run it under a time limit, its output and exit status in the log
    local limit=$1
    shift
    echo "== $(date -u +%H:%M:%S) $*" | tee -a "$log"
    timeout "$limit" "$@" 2>&1 | tee -a "$log"
    echo "== exit ${PIPESTATUS[0]}" | tee -a "$log"
}
step 30 nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv
step 120 "$py" -m pytest -q -p no:cacheprovider tests/test_cuda.py
step 240 "$py" benchmarks/rigid_body.py --device cuda --skip-finite --no-progress \
    --note "One GPU; benchmarks/cuda.sh." --out "$out/rigid_body"
step 180 "$py" benchmarks/dimension.py --device cuda --ladder 2,4,8,12,16 --converse "" --compare "" \
    --no-progress --out "$out/dimension"
