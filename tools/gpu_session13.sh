#!/bin/bash
# Session 13's second lent-GPU job, detached so it runs on between calls (see gpu_run.sh):
#   bash tools/gpu_session13.sh start     then   bash tools/gpu_session13.sh collect SECONDS
# 1. the warm 3-task warp profile of eval/reports/gpu_h100_session13 again, after the shared
#    planner: a first run builds warp's kernels and fills JAX's cache, the second is timed;
# 2. the full VLA export (18 seen tasks x 200 demos, keyframes, 128 px, five cameras).
export PYTHONPATH=/tmp/site:/tmp/agnostos/src MUJOCO_GL=egl AGNOSTOS_JAX_CACHE=/tmp/agnostos/jax_cache
export __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
R=/tmp/agnostos/s13
case "$1" in
  start)
    mkdir -p /tmp/agnostos/src $R && cp -r agnostos_mjx scenes pyproject.toml /tmp/agnostos/src/
    cat > $R/job.sh <<'JOB'
cd /tmp/agnostos/src
R=/tmp/agnostos/s13
filter() { grep --line-buffered -v "^Module\|solver iter\|linesearch\|warn_overflow"; }
for run in warm3_first warm3_second; do
  t0=$SECONDS
  XLA_PYTHON_CLIENT_MEM_FRACTION=0.4 python3 -m cProfile -o $R/$run.pstats -m agnostos_mjx.eval \
    --batch 75 --backend warp --tasks lamp_on,close_fridge,phone_on_base --quiet --out $R/$run 2>&1 | filter > $R/$run.log
  echo "$run wall $((SECONDS - t0)) s" >> $R/summary.txt
done
t0=$SECONDS
python3 -m agnostos_mjx.data.export --out /tmp/agnostos/export --tasks seen --demos 200 --size 128 \
  --workers 16 > $R/export.log 2>&1
echo "export exit $? wall $((SECONDS - t0)) s size $(du -sb /tmp/agnostos/export | cut -f1) bytes files $(find /tmp/agnostos/export -type f | wc -l)" >> $R/summary.txt
cp /tmp/agnostos/export/manifest.json $R/export_manifest.json
echo done >> $R/summary.txt
JOB
    (setsid nohup bash $R/job.sh > $R/job.out 2>&1 < /dev/null &)
    echo started ;;
  collect)
    end=$((SECONDS + $2))
    while ! grep -q "^done" $R/summary.txt 2>/dev/null && [ $SECONDS -lt $end ]; do sleep 5; done
    cat $R/summary.txt 2>/dev/null; tail -3 $R/export.log 2>/dev/null
    mkdir -p "$OUT/s13" && cp $R/*.txt $R/*.log $R/*.pstats $R/*.json "$OUT/s13/" 2>/dev/null
    for d in $R/warm3_*/; do [ -d "$d" ] && tar -C $R -czf "$OUT/s13/$(basename $d).tgz" "$(basename $d)"; done
    true ;;
esac
