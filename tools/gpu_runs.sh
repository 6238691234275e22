#!/bin/bash
# The benchmarks of eval/reports on a lent GPU host, one stage per device call (the machine
# goes back after a while without a call; stages that share a machine reuse its caches).
# Setup first (tools/gpu_setup.sh):
#   carry .gl .whl   bash tools/gpu_setup.sh base  (or gl, then whl)
#   carry .warp/pK   bash tools/gpu_setup.sh K     (K = 0..3; warp only)
# Stages (OUT: the folder that comes back; runs live in /tmp/agnostos):
#   astyped      the README's commands as a user types them, on a fresh machine (its first
#                stage): the main job (fresh), the 3-task dense image run of
#                tools/closed_loop_bench.py 4 times (the first builds Warp's render kernels),
#                the main job again (warm); each command's wall beside the run's own
#                (results.json wall_s), splits, and fresh-against-warm records
#   fresh1       GPU 0, a fresh machine: the main job alone (warp, 8 processes, MPS; it builds
#                Warp's kernels itself first); WARM=1 runs it once more, warm
#   fresh        GPU 0: python -m agnostos_mjx.warmup (warp), then the main job as fresh1
#   warm         GPU 0: the main job again (caches on disk), then native, 8 processes
#   native_host  GPU 0: native, 8 processes, with the numpy planner
#   scale        warp, then native: the main job on all GPUs (16 processes) and on GPU 0 (8)
#   kbuild       GPU 0: Warp's kernels of the 23 unseen scenes, each from an empty cache,
#                with KJOBS processes ("16 8" by default)
#   warmup       GPU 0: python -m agnostos_mjx.warmup --tasks unseen --backend warp
#   obs          observation benchmark: GPU 0 alone, then one process per GPU at once
#                (OBS_ARGS, default "--batches 1024 --renderers warp")
#   bank         the seen bank, 18 tasks x 200 demos, native, 16 worker processes + EGL
#   export       the VLA export of the 3,600 seen demos, 16 workers
#   vla_start    the reference VLA's data, precision profile and training on GPU 1 (or the only
#                GPU), detached (train/vla_gpu.sh train); poll shows its progress
#   vla_eval1    the VLA on GPU 0: seen + unseen as one run, 16 processes, --compare RVT2
#   vla_eval     the VLA: seen tasks on GPU 0, unseen on GPU 1, at once, 10 processes each
#   lerobot      lerobot-eval through the plug-in, OpenGL against MJX-Warp
#                (eval/reports/lerobot_eval_h200/bench.py; after gpu_setup.sh lerobot1, lerobot2)
# Every main job is python -m agnostos_mjx.eval --batch 75 --resume --quiet --compare "X-ICM 7B"
# plus the stage's flags, into $R/main_LABEL (at most LIMIT_S s; rerun to resume); its wall
# goes to $OUT/walls.txt and its folder, as a .tgz, to $OUT.
# CPUS=0-15 pins a stage's processes to those cores (taskset), e.g. to run as a 16-core
# one-GPU host on one GPU of a 32-core 2-GPU host; vla_start pins itself to VLA_CPUS (the
# other half of the cores on a host with >= 32).
# A stage run under `timeout` can leave the run's worker processes alive (they start with setsid);
# a later stage on the same machine then fails with CUDA errors.
set -e
: "${OUT:?set OUT}"
export PYTHONPATH=/tmp/site:$PWD MUJOCO_GL=egl AGNOSTOS_JAX_CACHE=/tmp/agnostos/jax_cache
export __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
R=/tmp/agnostos
mkdir -p $R "$OUT"
pin() { if [ -n "$CPUS" ]; then taskset -c "$CPUS" "$@"; else "$@"; fi; }
quiet() { grep --line-buffered -v 'solver iterations\|warn_overflow\|linesearch iterations\|^Module \|^   '; }
poll() {
  echo "-- VLA background job:"; tail -4 $R/vla_bg.log 2>/dev/null || true
  cat $R/vla_out/vla_timings.txt 2>/dev/null || true; tail -1 $R/vla_run/log.jsonl 2>/dev/null || true
  nvidia-smi --query-gpu=index,utilization.gpu,memory.used --format=csv,noheader
}
main() {  # main LABEL BACKEND ARGS...: the main job into $R/main_LABEL (at most $LIMIT_S s;
  # rerun to resume), its wall time and time split
  local label=$1 b=$2 d=$R/main_$1 t0=$SECONDS; shift 2; mkdir -p $d
  pin timeout ${LIMIT_S:-590} python3 -m agnostos_mjx.eval --batch 75 --backend $b --resume --quiet --out $d \
    --compare "X-ICM 7B" "$@" 2>&1 | quiet | tail -12 || true
  echo "main job $label ($b $* ${CPUS:+cores $CPUS}) wall $((SECONDS - t0)) s" | tee -a $d/wall.txt $OUT/walls.txt
  python3 -m agnostos_mjx.evaluation.timings $d | tail -1 || true
  tar -C $R --exclude='*.mp4' -czf "$OUT/main_$label.tgz" main_$label
}
warmup() {
  local t0=$SECONDS
  CUDA_VISIBLE_DEVICES=0 pin python3 -m agnostos_mjx.warmup --tasks unseen --backend warp --jobs 8 \
    2>&1 | quiet | tail -8
  echo "warmup (fresh machine${CPUS:+, cores $CPUS}) wall $((SECONDS - t0)) s" | tee -a $OUT/walls.txt
}
vla() {  # vla GPU SPLIT PROCS: the VLA's protocol evaluation (train/vla_gpu.sh eval SPLIT)
  local t0=$SECONDS
  CUDA_VISIBLE_DEVICES=$1 OUT=$OUT/vla_eval_$2 VLA_ROOT=$R VLA_CHECKPOINT=$R/vla_run \
    VLA_PROCS=$3 pin bash train/vla_gpu.sh eval $2 || true
  echo "vla eval $2 (GPU $1${CPUS:+, cores $CPUS}, $3 processes) wall $((SECONDS - t0)) s" \
    | tee -a $OUT/walls.txt
  python3 -m agnostos_mjx.evaluation.timings $R/vla_eval_$2 | tail -1 || true
}
vla_collect() {  # vla_collect SPLIT...: the runs, logs, curve and export back in $OUT
  for s in "$@"; do
    tar -C $R --exclude='*.mp4' --exclude=mps -czf "$OUT/vla_eval_$s.tgz" vla_eval_$s
  done
  OUT=$R/vla_out VLA_ROOT=$R bash train/vla_gpu.sh collect || true
  tar -C $R -czf "$OUT/vla_out.tgz" vla_out
}
astyped() {  # astyped LABEL ARGS...: python -m agnostos_mjx.eval ARGS into $R/LABEL, timed
  local label=$1 d=$R/$1 t0; shift; t0=$(date +%s.%N)
  timeout ${LIMIT_S:-300} python3 -m agnostos_mjx.eval "$@" --quiet --out $d 2>&1 | quiet | tail -1
  python3 - "$label" "$t0" "$(date +%s.%N)" "$d" <<'PY' | tee -a $OUT/walls.txt
import json, sys
label, t0, t1, d = sys.argv[1:]
run = json.load(open(f"{d}/results.json")).get("wall_s")
print(f"{label}: command {float(t1) - float(t0):.1f} s, the run's own wall {run} s")
PY
  python3 -m agnostos_mjx.evaluation.timings $d > $OUT/${label}_split.md 2>&1 || true
}
case "$1" in
  astyped)
    astyped main_fresh --batch 75
    for i in 0 1 2 3; do
      astyped loop$i --policy timing --policy-arg cameras=front,wrist --policy-arg size=128 \
        --policy-arg chunk=1 --action-mode dense --dense-steps 300 --seeds 0 --episodes 75 \
        --batch 75 --tasks lamp_on,close_microwave,put_knife_on_chopping_board
    done
    astyped main_warm --batch 75
    python3 tools/records_diff.py $R/main_fresh $R/main_warm | tail -1 | tee -a $OUT/walls.txt ;;
  vla_start)  # data, the precision profile and training on GPU 1 (or the only GPU), detached
    rm -rf $R/src && mkdir -p $R/src $R/vla_out
    pkill -f vla_gpu.sh || true; pkill -f vla_step_profile || true
    cp -a agnostos_mjx tools train scenes pyproject.toml $R/src/
    cpus=${VLA_CPUS:-$([ "$(nproc)" -ge 32 ] && echo "$(($(nproc) / 2))-$(($(nproc) - 1))" || echo "0-$(($(nproc) - 1))")}
    gpu=$(( $(nvidia-smi -L | grep -c '^GPU') > 1 ? 1 : 0 ))  # GPU 1, or the only one
    (cd $R/src && CUDA_VISIBLE_DEVICES=$gpu OUT=$R/vla_out VLA_ROOT=$R VLA_CALL_S=${VLA_CALL_S:-1500} \
      VLA_QUICK_TASKS= VLA_PRECISION=${VLA_PRECISION:-auto} PYTHONPATH=/tmp/site:$R/src \
      XLA_PYTHON_CLIENT_PREALLOCATE=false setsid nohup taskset -c $cpus bash train/vla_gpu.sh train \
      > $R/vla_bg.log 2>&1 < /dev/null &)
    sleep 20; poll ;;
  lerobot)
    HF_HUB_OFFLINE=1 HF_HOME=$R/hf python3 eval/reports/lerobot_eval_h200/bench.py \
      --dataset /tmp/lrw/agnostos_seen --out $R/lerobot --lerobot-eval /tmp/lerobot-eval 2>&1 | quiet | tail -8
    cp $R/lerobot/results.json $OUT/lerobot_results.json ;;
  poll) poll ;;
  warmup) warmup; poll ;;
  kbuild)
    for n in ${KJOBS:-16 8}; do
      t0=$SECONDS
      WARP_CACHE_PATH=$R/kcache_p$n CUDA_VISIBLE_DEVICES=0 pin python3 -m agnostos_mjx.warmup \
        --task-runs none --policy none --tasks unseen --kernel-jobs $n 2>&1 | quiet | tail -1 | tee -a $OUT/kbuild.log
      echo "kernels of the unseen scenes, $n processes, wall $((SECONDS - t0)) s" | tee -a $OUT/walls.txt
    done ;;
  fresh)
    t0=$SECONDS
    warmup
    CUDA_VISIBLE_DEVICES=0 main fresh warp --local-processes 8 --mps on
    echo "fresh total (warmup + main job) $((SECONDS - t0)) s" | tee -a $OUT/walls.txt; poll ;;
  fresh1)
    CUDA_VISIBLE_DEVICES=0 main fresh1 warp --local-processes 8 --mps on
    [ -z "$WARM" ] || CUDA_VISIBLE_DEVICES=0 main warm1 warp --local-processes 8 --mps on ;;
  warm)
    CUDA_VISIBLE_DEVICES=0 main warm warp --local-processes 8 --mps on
    poll
    CUDA_VISIBLE_DEVICES=0 LIMIT_S=${NATIVE_S:-330} main native native --local-processes 8
    poll ;;
  scale)
    main scale2 warp --local-processes 16 --mps on
    CUDA_VISIBLE_DEVICES=0 main scale1 warp --local-processes 8 --mps on
    LIMIT_S=${NATIVE_S:-150} main scale2_native native --local-processes 16
    CUDA_VISIBLE_DEVICES=0 LIMIT_S=${NATIVE_S:-150} main scale1_native native --local-processes 8
    poll ;;
  native_host) CUDA_VISIBLE_DEVICES=0 LIMIT_S=${LIMIT_S:-420} main native_host native \
      --local-processes 8 --planner host; poll ;;
  obs)
    bench() {  # bench GPU LABEL
      CUDA_VISIBLE_DEVICES=$1 python3 -m agnostos_mjx.bench.observation ${OBS_ARGS:---batches 1024 --renderers warp} \
        --out "$OUT/obs_$2.json" > "$OUT/obs_$2.log" 2>&1
      echo "observation bench $2 exit $?" | tee -a $OUT/walls.txt
    }
    bench 0 gpu0_alone
    n=$(nvidia-smi -L | grep -c '^GPU')
    for k in $(seq 0 $((n - 1))); do bench $k "gpu${k}_of_$n" & done; wait
    tail -n 3 "$OUT"/obs_*.log ;;
  bank)
    t0=$SECONDS
    pin python3 -m agnostos_mjx.data.generate --out $R/bank --tasks seen --demos ${DEMOS:-200} --batch 50 \
      --workers 16 --backend native --quiet 2>&1 | quiet | tail -30
    echo "seen bank wall $((SECONDS - t0)) s" | tee -a $OUT/walls.txt
    mkdir -p "$OUT/bank"; cp $R/bank/report.md $R/bank/manifest.json "$OUT/bank/" ;;
  export)
    t0=$SECONDS
    pin python3 -m agnostos_mjx.data.export --out $R/export --tasks seen --demos ${DEMOS:-200} --size 128 \
      --workers 16 2>&1 | quiet | tail -5
    echo "export wall $((SECONDS - t0)) s, $(du -sb $R/export | cut -f1) bytes" | tee -a $OUT/walls.txt
    cp $R/export/manifest.json "$OUT/export_manifest.json" ;;
  vla_eval1)  # one H100: GPU 0 (and, with CPUS, its share of the cores), both splits as one run
    vla 0 all ${VLA_PROCS:-16}; vla_collect all ;;
  vla_eval)  # one split per GPU, at once
    vla 0 seen 10 & vla 1 unseen 10 & wait; vla_collect seen unseen ;;
  *) echo "usage: bash tools/gpu_runs.sh fresh1|fresh|warm|native_host|scale|kbuild|warmup|obs|bank|export|vla_start|poll|vla_eval1|vla_eval" >&2; exit 2 ;;
esac
