#!/bin/bash
# Session 14's lent-GPU job, detached so it runs on between calls (see gpu_run.sh):
#   bash tools/gpu_session14.sh start     then   bash tools/gpu_session14.sh collect SECONDS
# 1. the observation benchmark (full RLBench observation vs the bare MJX-Warp renderer) after
#    the warp observation became one program posed by kinematics + fixed camera poses;
# 2. the warp-vs-CPU image agreement test (slow, prints the pixel-difference figures);
# 3. oracle key actions at batch 75, native vs warp, under Warp's graph modes WARP_STAGED
#    (the default) and JAX (XLA captures the FFI into its own command buffers), the latter
#    also with XLA's command buffers extended to while loops.
export PYTHONPATH=/tmp/site:/tmp/agnostos/src MUJOCO_GL=egl AGNOSTOS_JAX_CACHE=/tmp/agnostos/jax_cache
export __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
R=/tmp/agnostos/s14
case "$1" in
  start)
    mkdir -p /tmp/agnostos/src $R && cp -r agnostos_mjx scenes tests pyproject.toml /tmp/agnostos/src/
    cat > $R/job.sh <<'JOB'
cd /tmp/agnostos/src
R=/tmp/agnostos/s14
filter() { grep --line-buffered -v "^Module\|solver iter\|linesearch\|warn_overflow"; }
t0=$SECONDS
python3 -m agnostos_mjx.observation_bench --renderers warp --repeats 5 \
  --out $R/observation_bench_h100.json 2>&1 | filter > $R/observation_bench.log
echo "observation_bench exit ${PIPESTATUS[0]} wall $((SECONDS - t0)) s" >> $R/summary.txt
if python3 -c "import pytest" 2>/dev/null; then
  python3 -m pytest -q -s -m slow -p no:cacheprovider tests/test_observation.py -k warp_matches \
    2>&1 | filter > $R/warp_matches_cpu.log
  echo "warp_matches_cpu: $(tail -1 $R/warp_matches_cpu.log)" >> $R/summary.txt
fi
for mode in WARP_STAGED JAX JAX_WHILE; do
  t0=$SECONDS
  backends=warp; [ $mode = WARP_STAGED ] && backends=native,warp
  flags=""; [ $mode = JAX_WHILE ] && flags="--xla_gpu_enable_command_buffer=FUSION,CUBLAS,CUBLASLT,CUSTOM_CALL,WHILE,CONDITIONAL"
  AGNOSTOS_WARP_GRAPH_MODE=${mode%_WHILE} XLA_FLAGS="$flags" timeout 900 python3 -m agnostos_mjx.bench \
    --tasks lamp_on,stack_blocks --backends $backends --batches 75 --out $R/bench_$mode.json 2>&1 \
    | filter > $R/bench_$mode.log
  echo "bench $mode exit ${PIPESTATUS[0]} wall $((SECONDS - t0)) s" >> $R/summary.txt
done
echo done >> $R/summary.txt
JOB
    (setsid nohup bash $R/job.sh > $R/job.out 2>&1 < /dev/null &)
    echo started ;;
  obs)  # steps 1 and 2 only, in the foreground
    mkdir -p /tmp/agnostos/src $R "$OUT/s14" && cp -r agnostos_mjx scenes tests pyproject.toml /tmp/agnostos/src/
    cd /tmp/agnostos/src
    python3 -m agnostos_mjx.observation_bench --renderers warp --repeats 5 \
      --out "$OUT/s14/observation_bench_h100.json" 2>&1 | grep -v "^Module\|warn_overflow" | tail -20
    python3 -m pytest -q -s -m slow -p no:cacheprovider tests/test_observation.py -k warp_matches \
      2>&1 | tail -15 ;;
  collect)
    end=$((SECONDS + $2))
    while ! grep -q "^done" $R/summary.txt 2>/dev/null && [ $SECONDS -lt $end ]; do sleep 5; done
    cat $R/summary.txt 2>/dev/null; tail -12 $R/observation_bench.log 2>/dev/null
    for f in $R/bench_*.log; do echo "== $f"; tail -8 "$f"; done 2>/dev/null
    mkdir -p "$OUT/s14" && cp $R/*.txt $R/*.log $R/*.json $R/job.out "$OUT/s14/" 2>/dev/null
    true ;;
esac
