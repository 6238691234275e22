#!/bin/bash
# Steps run on the lent GPU machine after tools/gpu_setup.sh (see README "GPU").
#   bash tools/gpu_run.sh oracle-native      oracle reports of every implemented task, native CPU
#   bash tools/gpu_run.sh oracle-warp TASKS  oracle on TASKS with the warp backend
#   bash tools/gpu_run.sh bank DEMOS         the seen-task bank (native physics in 16 processes, EGL)
#   bash tools/gpu_run.sh bank-warp TASKS DEMOS   a bank of TASKS with the warp backend
#   bash tools/gpu_run.sh default BACKEND     the main job (python -m agnostos_mjx.eval --batch 75)
#   bash tools/gpu_run.sh bench               oracle key actions warp vs native at batch 75, reset of 8,192
#   bash tools/gpu_run.sh start BACKEND[:LABEL]...  the main job per BACKEND, one after the other,
#                                             detached: it runs on between calls while the
#                                             machine stays warm (start twice to overlap)
#   bash tools/gpu_run.sh parallel N BACKEND:LABEL   the main job as N processes sharing the GPU
#                                             (--num-processes N, then --merge), detached
#   bash tools/gpu_run.sh collect SECONDS     wait up to SECONDS for detached runs, then bring
#                                             back each run's folder (log, results, episodes)
# Outputs go to $OUT (what comes back) and /tmp/agnostos (kept while the machine is warm).
set -e
export PYTHONPATH=/tmp/site:$PWD MUJOCO_GL=egl
export __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
export AGNOSTOS_JAX_CACHE=/tmp/agnostos/jax_cache
mkdir -p /tmp/agnostos "$OUT"
case "$1" in
  oracle-native)
    for split in seen unseen; do
      t0=$SECONDS; python3 -m agnostos_mjx.eval --policy oracle --tasks $split \
        --variations all --backend native --batch 75 --quiet --out /tmp/agnostos/oracle_$split \
        2>&1 | tail -60; echo "wall $((SECONDS - t0)) s"
      tar -C /tmp/agnostos -czf "$OUT/oracle_$split.tgz" oracle_$split
    done ;;
  oracle-warp)
    t0=$SECONDS; python3 -m agnostos_mjx.eval --policy oracle --tasks "$2" \
      --variations all --backend warp --batch 75 --quiet --out /tmp/agnostos/warp_$3 2>&1 | tail -30; echo "wall $((SECONDS - t0)) s"
    tar -C /tmp/agnostos -czf "$OUT/warp_$3.tgz" warp_$3 ;;
  bank)
    tasks=$(python3 -c "from agnostos_mjx.tasks import list_tasks; print(','.join(list_tasks('seen')))")
    t0=$SECONDS; python3 -m agnostos_mjx.data.generate --out /tmp/agnostos/bank \
      --tasks "$tasks" --demos "$2" --batch 50 --workers 16 --backend native --quiet 2>&1 | tail -30; echo "wall $((SECONDS - t0)) s"
    mkdir -p "$OUT/bank"; cp /tmp/agnostos/bank/report.md /tmp/agnostos/bank/manifest.json "$OUT/bank/" ;;
  bank-warp)
    t0=$SECONDS; python3 -m agnostos_mjx.data.generate --out /tmp/agnostos/bank_warp \
      --tasks "$2" --demos "$3" --batch 200 --backend warp --quiet 2>&1 | grep -v "solver iterations\|warn_overflow" | tail -30; echo "wall $((SECONDS - t0)) s"
    mkdir -p "$OUT/bank_warp"; cp /tmp/agnostos/bank_warp/report.md /tmp/agnostos/bank_warp/manifest.json "$OUT/bank_warp/" ;;
  default)
    t0=$SECONDS; python3 -m agnostos_mjx.eval --batch 75 --backend "$2" --resume --quiet \
      --compare "X-ICM 7B" --out /tmp/agnostos/default_$2 2>&1 | grep -v "solver iterations\|warn_overflow" | tail -45
    echo "wall $((SECONDS - t0)) s"
    tar -C /tmp/agnostos -czf "$OUT/default_$2.tgz" default_$2 ;;
  bench)  # key-action throughput, warp against native, then the reset of 8,192 worlds
    t0=$SECONDS; python3 -m agnostos_mjx.bench --tasks lamp_on,stack_blocks --backends native,warp \
      --batches 75 --out "$OUT/bench_75.json" 2>&1 | grep -v "solver iterations\|warn_overflow" | tail -12
    python3 -m agnostos_mjx.bench --tasks stack_blocks --backends warp --batches 8192 \
      --reset-only 8192 --out "$OUT/reset_8192.json" 2>&1 | grep -v "solver iterations\|warn_overflow" | tail -6
    echo "wall $((SECONDS - t0)) s" ;;
  start)
    # Run from a private copy: the call's working tree may be replaced by the next call.
    mkdir -p /tmp/agnostos/src && cp -r agnostos_mjx scenes pyproject.toml /tmp/agnostos/src/
    job=""
    for spec in "${@:2}"; do  # BACKEND or BACKEND:LABEL (e.g. warp:cold warp:warm)
      b=${spec%%:*}; label=${spec#*:}
      mkdir -p /tmp/agnostos/default_$label
      py="python3"  # a LABEL with "prof" in it runs under cProfile (profile.pstats)
      [[ $label == *prof* ]] && py="python3 -m cProfile -o /tmp/agnostos/default_$label/profile.pstats"
      job+="t0=\$SECONDS; $py -m agnostos_mjx.eval --batch 75 --backend $b --resume \
        --quiet --compare 'X-ICM 7B' --out /tmp/agnostos/default_$label 2>&1 \
        | grep --line-buffered -v 'solver iterations\|warn_overflow\|linesearch iterations' \
        >> /tmp/agnostos/default_$label/log.txt; echo \"exit \${PIPESTATUS[0]} wall \$((SECONDS - t0)) s\" \
        >> /tmp/agnostos/default_$label/log.txt; "
    done
    (cd /tmp/agnostos/src && PYTHONPATH=/tmp/site:/tmp/agnostos/src \
      XLA_PYTHON_CLIENT_MEM_FRACTION=0.4 setsid nohup bash -c "$job" > /dev/null 2>&1 < /dev/null &)
    echo "started ${*:2} (one after the other)" ;;
  parallel)  # parallel N BACKEND:LABEL: the main job split over N processes sharing the GPU
    n=$2; b=${3%%:*}; label=${3#*:}; R=/tmp/agnostos/default_$label
    mkdir -p /tmp/agnostos/src $R && cp -r agnostos_mjx scenes pyproject.toml /tmp/agnostos/src/
    frac=$(python3 -c "print(round(0.6 / $n, 3))")  # Warp allocates its CUDA graphs outside the pool
    job="cd /tmp/agnostos/src; t0=\$SECONDS; "
    for i in $(seq 0 $((n - 1))); do
      job+="python3 -m agnostos_mjx.eval --batch 75 --backend $b --resume --quiet \
        --num-processes $n --process-id $i --gpu-mem-fraction $frac --out $R \
        2>&1 | grep --line-buffered -v 'solver iterations\|warn_overflow\|linesearch\|^Module' \
        > $R/proc$i.log & "
    done
    job+="wait; python3 -m agnostos_mjx.eval --out $R --merge --compare 'X-ICM 7B' > $R/log.txt 2>&1; \
      echo \"exit \$? wall \$((SECONDS - t0)) s ($n processes)\" >> $R/log.txt"
    (PYTHONPATH=/tmp/site:/tmp/agnostos/src setsid nohup bash -c "$job" > /dev/null 2>&1 < /dev/null &)
    echo "started $n processes of the main job ($b) into $R" ;;
  collect)
    end=$((SECONDS + $2))
    while pgrep -f "agnostos_mjx[.]eval" > /dev/null && [ $SECONDS -lt $end ]; do sleep 5; done
    for d in /tmp/agnostos/default_*/; do
      n=$(basename "$d"); echo "== $n"; tail -8 "$d/log.txt"
      tar -C /tmp/agnostos -czf "$OUT/$n.tgz" "$n"
    done
    pgrep -fa "agnostos_mjx[.]eval" | cut -c1-120 || echo "no run still going" ;;
esac
