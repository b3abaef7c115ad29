#!/usr/bin/env bash
# Issue #18's checks on one GPU, in one go (a lent GPU machine has a few minutes; this is sized to fit ten):
#   1. the package's CUDA tests (tests/test_cuda.py: the same seed gives the CPU's numbers, checkpoints move);
#   2. two tiny end-to-end runs of rigid_body.py and dimension.py on the GPU: if one fails, its long runs are
#      skipped (the failure is in the log, and the device time is kept for a rerun);
#   3. the rigid body's main run on the GPU (benchmarks/rigid_body.py --device cuda, infinite horizon only),
#      whose goals table then carries the "under 3 minutes on one GPU";
#   4. the lowest-error rigid-body setting of the CPU runs (3 x 48, 6400 points, no stall rule, the 1.3x box);
#   5. the LQ ladder at n = 2, 4, 8, 12, 16 on the GPU (benchmarks/dimension.py --device cuda).
# Each step has its own time limit and the next runs whatever the last did; all output goes to one log.
#
#   bash benchmarks/cuda.sh                # results under benchmarks/results/cuda_nd/
#   OUT=/some/dir bash benchmarks/cuda.sh  # or there (the device tool's $OUT)
#
# Needs python3 with torch (CUDA), numpy, scipy, tqdm, matplotlib and pytest; PYTHON= picks another interpreter.
set -uo pipefail
out=${OUT:-benchmarks/results/cuda_nd}
py=${PYTHON:-python3}
mkdir -p "$out/rigid_body" "$out/rigid_body_best" "$out/dimension"
export PYTHONUNBUFFERED=1 PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
log="$out/log.txt"
: >"$log"
step() {  # step SECONDS COMMAND...: run it under a time limit, its output and exit status in the log
    local limit=$1
    shift
    echo "== $(date -u +%H:%M:%S) $*" | tee -a "$log"
    timeout "$limit" "$@" 2>&1 | tee -a "$log"
    local rc=${PIPESTATUS[0]}
    echo "== exit $rc" | tee -a "$log"
    return "$rc"
}
smoke=$(mktemp -d)
step 15 nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv
step 80 "$py" -m pytest -q -p no:cacheprovider tests/test_cuda.py
step 45 "$py" benchmarks/rigid_body.py --device cuda --width 8 --points 300 --max-horizon 4 --step 2 --lm-steps 5 \
    --min-progress none --closed-loop 4 --t-final 2 --budget-states 2 --skip-finite --no-progress --out "$smoke/rb"
rb=$?
step 40 "$py" benchmarks/dimension.py --device cuda --ladder 4 --converse "" --compare "" --max-horizon 2 \
    --lm-steps 5 --min-progress none --no-progress --out "$smoke/dim"
dim=$?
if [ "$rb" = 0 ]; then
    step 140 "$py" benchmarks/rigid_body.py --device cuda --skip-finite --no-progress \
        --note "One GPU; benchmarks/cuda.sh." --out "$out/rigid_body"
    step 160 "$py" benchmarks/rigid_body.py --device cuda --width 48 --points 6400 --min-progress none \
        --lm-steps 150 --skip-finite --max-time 4000 --train-scale 1.3,1.2,1.3,1.1,1.1,1.1 --no-progress \
        --note "One GPU; benchmarks/cuda.sh." --out "$out/rigid_body_best"
fi
if [ "$dim" = 0 ]; then
    step 100 "$py" benchmarks/dimension.py --device cuda --ladder 2,4,8,12,16 --converse "" --compare "" \
        --no-progress --out "$out/dimension"
fi
