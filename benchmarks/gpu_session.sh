#!/usr/bin/env bash
# One prepared run for a lent GPU machine (the `device` tool): a time-boxed
# `trainer=paper` run of the default scene, then the zoo at the paper's settings (every
# backbone, without skipping unless GPU_ZOO_SKIP says) in what is left of the call.
#
#   here:  make gpu-kit     # the wheels the GPU image lacks (hydra-core, omegaconf, antlr4) -> .whl/
#   there: bash benchmarks/gpu_session.sh      with carry [".whl"], timeout_s ~580
#
# The GPU image has its own torch (CUDA), lightning, numba, scipy, scikit-image and
# matplotlib; the project runs from the checkout (PYTHONPATH), nothing else is installed.
# Everything lands in $OUT (at most 8 files come back): env.txt, zoo_cuda.md/.json,
# zoo.log, paper_train.log, paper_metrics.json, paper_curve.csv.
#
# GPU_SESSION_DEVICE=cpu runs the same plumbing on a CPU at toy sizes (a check that the
# script itself works; its figures mean nothing).
set -uo pipefail
OUT=${OUT:-/tmp/gpu_session}
DEVICE=${GPU_SESSION_DEVICE:-cuda}
TRAIN_MIN=${GPU_TRAIN_MINUTES:-3}      # training wall-clock of the trainer=paper run (first)
ZOO_BUDGETS=${GPU_ZOO_BUDGETS:-"10 30"}
# render.skip=none only (GPU_ZOO_SKIP="none grid" for both): session 36 timed both modes on
# an H100, the grid did not pay in the first 30 s (docs/results/gpu.md), and with both
# modes the zoo ran out of time before HexPlane
ZOO_SKIP=${GPU_ZOO_SKIP:-none}
ZOO_ONLY=${GPU_ZOO_ONLY:-}             # a subset of backbones for the zoo (default: all four)
TOTAL_S=${GPU_SESSION_SECONDS:-560}   # the whole script, inside the device call's timeout_s
PY=${PYTHON:-python3}
T_START=$(date +%s)
mkdir -p "$OUT"
if compgen -G ".whl/*.whl" >/dev/null; then
  "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
      --target /tmp/gpu_site .whl/*.whl || exit 1
  export PYTHONPATH=/tmp/gpu_site:${PYTHONPATH:-}
fi
export PYTHONPATH=$PWD/src:$PWD:${PYTHONPATH:-} PYTHONUNBUFFERED=1 EVENTRECON_OFFLINE=1
{ date -u; nvidia-smi 2>&1 | head -15
  "$PY" -c "import torch, lightning, hydra; print('torch', torch.__version__, 'cuda',
torch.cuda.is_available(), torch.cuda.get_device_name(0) if torch.cuda.is_available() else '-',
'| lightning', lightning.__version__, '| hydra', hydra.__version__)"; } > "$OUT/env.txt" 2>&1
cat "$OUT/env.txt"

if [ "$DEVICE" = cuda ]; then
  # shellcheck disable=SC2206
  ZOO=(--device cuda --skip $ZOO_SKIP --images 1 --reps 5)
  # shellcheck disable=SC2206
  [ -n "$ZOO_ONLY" ] && ZOO+=(--only $ZOO_ONLY)
  TRAIN=(trainer=paper)
else
  ZOO=(--device cpu --only nerf --skip none --images 1 --warmup 1 --reps 2 --threads 1)
  TRAIN=(scale=smoke)
fi
t0=$(date +%s)
RUN=/tmp/gpu_session_run
rm -rf "$RUN"
"$PY" train.py "${TRAIN[@]}" "trainer.lightning.max_time=00:00:$(printf %02d "$TRAIN_MIN"):00" \
    logger=tensorboard "hydra.run.dir=$RUN" > "$OUT/paper_train.log" 2>&1
echo "train: rc $? in $(( $(date +%s) - t0 )) s"; tail -n 30 "$OUT/paper_train.log"
cp "$RUN/metrics.json" "$OUT/paper_metrics.json" 2>/dev/null
cp "$RUN/curve.csv" "$OUT/paper_curve.csv" 2>/dev/null

# the zoo gets what is left of the call (its per-backbone lines reach zoo.log as they finish)
left=$(( TOTAL_S - ($(date +%s) - T_START) ))
t0=$(date +%s)
# shellcheck disable=SC2086
timeout "$left" "$PY" -m benchmarks zoo "${ZOO[@]}" --budgets $ZOO_BUDGETS \
    --out "$OUT/zoo_cuda.md" --json "$OUT/zoo_cuda.json" > "$OUT/zoo.log" 2>&1
echo "zoo: rc $? in $(( $(date +%s) - t0 )) s (of $left s left)"; tail -n 25 "$OUT/zoo.log"
ls -l "$OUT"
