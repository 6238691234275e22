#!/bin/bash
# The reference VLA (issue 28) on one lent GPU host, after `bash tools/gpu_setup.sh base`
# (EGL libraries, mujoco & co in /tmp/site; native physics only, no warp needed):
#   bash train/vla_gpu.sh train     keyframe data of the 18 seen tasks (16 processes), training
#                                   on the GPU until VLA_STEPS or the call's time budget
#                                   (VLA_CALL_S, 570 s, minus the data's time and a reserve),
#                                   the float16 export (~13 MB) to $OUT/vla_export, then a
#                                   quick check on 3 seen tasks x 5 episodes (VLA_QUICK_TASKS;
#                                   empty: none); rerun to resume (finished data chunks and
#                                   checkpoints are kept)
#   bash train/vla_gpu.sh eval [all|seen|unseen]   the protocol: the seen and unseen tasks
#                                   as one run (or one split), 3 seeds x 25 episodes,
#                                   with the paper's RVT2 row (--compare); on a fresh machine
#                                   carry the export back and set VLA_CHECKPOINT=its folder
#   bash train/vla_gpu.sh collect   logs, curves, results and the export
# Settings (environment): VLA_DEMOS (100 per task), VLA_CAMERAS, VLA_SIZE (96 px), VLA_STEPS
# (8000), VLA_BATCH (32), VLA_EPISODES (25) and VLA_SEEDS (0,1,2) of the evaluation,
# VLA_WORKERS (data processes, 16), VLA_PRECISION (training matmuls: default, tensorfloat32,
# bfloat16, or auto: tools/vla_step_profile.py times them while the data are made and the
# fastest by > 10 % wins), VLA_EVAL_BATCH (75), VLA_BACKEND (native; warp: the GPU physics
# and renderer), VLA_PROCS (eval processes: 16, one H100's recipe; 1 with VLA_TINY),
# VLA_ROOT (/tmp/agnostos), VLA_EXTRA (more train.vla flags).
# A training stopped by the call's budget (log: "stopping at step") resumes where it
# stopped, on the same schedule, when `train` runs again on the same (warm) machine.
# VLA_TINY=1: 2 tasks x 2 demos, the --quick model and 2 episodes per task (the script's
# logic on a CPU, e.g. `OUT=/tmp/o VLA_TINY=1 bash train/vla_gpu.sh train`).
# Everything is logged to $OUT/vla_<stage>.log with the wall time of each stage.
set -eo pipefail
: "${OUT:?set OUT (the folder that comes back)}"
ROOT=${VLA_ROOT:-/tmp/agnostos}
DATA=$ROOT/vla_data RUN=$ROOT/vla_run
export PYTHONPATH=/tmp/site:$PWD${PYTHONPATH:+:$PYTHONPATH} MUJOCO_GL=${MUJOCO_GL:-egl}
[ -f /usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json ] && \
  export __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
export AGNOSTOS_JAX_CACHE=${AGNOSTOS_JAX_CACHE:-$ROOT/jax_cache}
PY=${PYTHON:-python3}
mkdir -p "$ROOT" "$OUT"
if [ -n "$VLA_TINY" ]; then
  TASKS=turn_tap,push_buttons UNSEEN=lamp_on DEMOS=2 EPISODES=2 SEEDS=0 QUICK=--quick
  WORKERS=2 CHUNK=1 CAMERAS=front,overhead SIZE=32 STEPS=${VLA_STEPS:-20}
else
  TASKS=seen UNSEEN=unseen DEMOS=${VLA_DEMOS:-100} QUICK=
  EPISODES=${VLA_EPISODES:-25} SEEDS=${VLA_SEEDS:-0,1,2}
  WORKERS=${VLA_WORKERS:-16} CHUNK=10 CAMERAS=${VLA_CAMERAS:-front,left_shoulder,right_shoulder,wrist}
  SIZE=${VLA_SIZE:-96} STEPS=${VLA_STEPS:-8000}
fi
BATCH=${VLA_BATCH:-32} EVAL_BATCH=${VLA_EVAL_BATCH:-75} BACKEND=${VLA_BACKEND:-native}
PROCS=${VLA_PROCS:-$([ -n "$VLA_TINY" ] && echo 1 || echo 16)} CALL_S=${VLA_CALL_S:-570} CKPT=${VLA_CHECKPOINT:-$RUN}
QUICK_TASKS=${VLA_QUICK_TASKS-open_drawer,push_buttons,turn_tap}

stage() {  # stage NAME COMMAND...: run, log to $OUT/vla_NAME.log, print the wall time
  local name=$1 t0=$SECONDS rc; shift
  echo "== $name: $*" | tee -a "$OUT/vla_$name.log"
  set +e
  "$@" 2>&1 | grep --line-buffered -v "solver iterations\|warn_overflow\|linesearch\|Failed to import" \
    | tee -a "$OUT/vla_$name.log" | tail -25
  rc=${PIPESTATUS[0]}
  set -e
  echo "== $name: exit $rc, wall $((SECONDS - t0)) s" | tee -a "$OUT/vla_$name.log" "$OUT/vla_timings.txt"
  return "$rc"
}

evaluate() {  # evaluate SPLIT LABEL EPISODES SEEDS [PROCS]
  local procs=(); [ "${5:-1}" -gt 1 ] && procs=(--local-processes "$5")
  stage "eval_$2" $PY -m agnostos_mjx.eval --policy reference-vla \
    --policy-arg checkpoint="$CKPT" --tasks "$1" --episodes "$3" --seeds "$4" \
    --batch "$EVAL_BATCH" --backend "$BACKEND" --resume --quiet "${procs[@]}" \
    --compare RVT2 --out "$ROOT/vla_eval_$2"
  mkdir -p "$OUT/eval_$2"
  cp "$ROOT/vla_eval_$2"/results.{md,csv,json,png} "$OUT/eval_$2/" 2>/dev/null || true
}

case "$1" in
  train)
    PRECISION=${VLA_PRECISION:-default}
    if [ "$PRECISION" = auto ]; then  # measure the step's precisions while the data are made
      XLA_PYTHON_CLIENT_PREALLOCATE=false $PY tools/vla_step_profile.py ${VLA_TINY:+--batch 2 --iters 1} --out "$OUT/step_profile.json" > "$OUT/vla_profile.log" 2>&1 &
      profile=$!
    fi
    # Up to 3 attempts: NVIDIA's EGL once refused a worker's framebuffer while other jobs held
    # most of the GPU's memory; finished chunks are kept, so an attempt does only the rest.
    # A usage error (exit 2) is not retried.
    for attempt in 1 2 3; do
      rc=0
      stage data $PY -m agnostos_mjx.train.vla_data --out "$DATA" --tasks "$TASKS" \
        --demos "$DEMOS" --cameras "$CAMERAS" --size "$SIZE" --chunk "$CHUNK" \
        --workers "$WORKERS" || rc=$?
      if [ $rc = 0 ]; then break; fi
      if [ $rc = 2 ] || [ $attempt = 3 ]; then exit $rc; fi
      echo "== data: attempt $attempt failed; again (finished chunks are kept)"
    done
    if [ "$PRECISION" = auto ]; then  # the fastest by >10 % over the default, else the default
      wait $profile || true
      PRECISION=$($PY -c "import json,sys
try: r = json.load(open(sys.argv[1]))
except Exception: print('default'); raise SystemExit
t = {k: r.get(f'train_step_{k}_ms', 1e9) for k in ('default', 'tensorfloat32', 'bfloat16')}
best = min(t, key=t.get)
print(best if t[best] < 0.9 * t['default'] else 'default')" "$OUT/step_profile.json")
      echo "== matmul precision: $PRECISION ($(cat "$OUT/step_profile.json" 2>/dev/null | tr -d '\n '))" \
        | tee -a "$OUT/vla_timings.txt"
    fi
    # What is left of the call after loading, compiling, the last checkpoint and the check.
    reserve=$((60 + (${#QUICK_TASKS} > 0 ? 90 : 0)))
    left=$((CALL_S - SECONDS - reserve)); [ $left -lt 30 ] && left=30
    stage train $PY -m agnostos_mjx.train.vla $QUICK --data "$DATA" --out "$RUN" \
      --steps "$STEPS" --batch-size "$BATCH" --max-seconds $left --no-progress \
      --export "$OUT/vla_export" --matmul-precision "$PRECISION" $VLA_EXTRA
    cp "$RUN"/log.jsonl "$RUN"/heldout.jsonl "$RUN"/config.json "$OUT/" 2>/dev/null || true
    if [ -n "$VLA_TINY" ]; then evaluate "$TASKS" quick "$EPISODES" 0
    elif [ -n "$QUICK_TASKS" ]; then evaluate "$QUICK_TASKS" quick 5 0; fi ;;
  eval)
    if [ ! -e "$CKPT" ]; then
      echo "no checkpoint at $CKPT (a fresh machine?): carry the export that 'train' wrote to" \
        "\$OUT/vla_export and set VLA_CHECKPOINT to its folder" >&2; exit 2
    fi
    # `eval` (all): the seen and unseen tasks as one run, so its processes start once and
    # one task queue balances all 41 tasks; `eval seen` / `eval unseen`: one split per call
    # when both do not fit one. --resume lets a call stopped by its limit continue.
    case "${2:-all}" in
      all) evaluate "$TASKS,$UNSEEN" all "$EPISODES" "$SEEDS" "$PROCS" ;;
      seen) evaluate "$TASKS" seen "$EPISODES" "$SEEDS" "$PROCS" ;;
      unseen) evaluate "$UNSEEN" unseen "$EPISODES" "$SEEDS" "$PROCS" ;;
      *) echo "usage: bash train/vla_gpu.sh eval [all|seen|unseen]" >&2; exit 2 ;;
    esac ;;
  collect)
    cp "$RUN"/log.jsonl "$RUN"/heldout.jsonl "$RUN"/config.json "$OUT/" 2>/dev/null || true
    [ -d "$OUT/vla_export" ] || $PY -m agnostos_mjx.train.vla --out "$RUN" --export "$OUT/vla_export"
    $PY -m agnostos_mjx.train.vla --out "$RUN" --curve | tee "$OUT/curve.md"
    cat "$OUT/vla_timings.txt" 2>/dev/null || true ;;
  *) echo "usage: bash train/vla_gpu.sh train|eval|collect" >&2; exit 2 ;;
esac
