#!/bin/bash
# The GPU physics-floor measurements of issue 26 on a lent H100 (one stage per device call;
# the machine stays warm 30 s between calls).  Outputs go to $OUT; runs to /tmp/agnostos.
#
# Setup first: tools/gpu_setup.sh base, then 0..3 (warp-lang), back to back.
# Stages:
#   bash tools/gpu_floor.sh ab          warmup (fresh-machine cold start) + graph mode / K A/B
#   bash tools/gpu_floor.sh warp LABEL [ARGS]   the main job on warp (extra eval ARGS)
#   bash tools/gpu_floor.sh native LABEL [ARGS] the main job on native MuJoCo (extra eval ARGS)
set -e
export PYTHONPATH=/tmp/site:$PWD MUJOCO_GL=egl AGNOSTOS_JAX_CACHE=/tmp/agnostos/jax_cache
export __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
mkdir -p /tmp/agnostos "$OUT"
quiet() { grep --line-buffered -v 'solver iterations\|warn_overflow\|linesearch iterations\|^Module \|^   '; }
case "$1" in
  ab)
    t0=$SECONDS
    python3 -m agnostos_mjx.warmup --tasks unseen --backend warp --jobs 8 2>&1 | quiet | tail -30
    echo "warmup (fresh machine) wall $((SECONDS - t0)) s"
    t0=$SECONDS
    timeout 300 python3 -u tools/warp_phase_ab.py --tasks lamp_on,stack_blocks --batch 75 \
      --variants WARP_STAGED:4,WARP_STAGED:16,WARP:16,WARP:64 --out "$OUT/ab_75.json" 2>&1 | quiet | grep '^{' || true
    timeout 150 python3 -u tools/warp_phase_ab.py --tasks lamp_on --batch 1024 --rounds 1 \
      --variants WARP_STAGED:16,WARP:16 --out "$OUT/ab_1024.json" 2>&1 | quiet | grep '^{' || true
    echo "a/b wall $((SECONDS - t0)) s" ;;
  warp|native)
    b=$1; label=$2; shift 2; R=/tmp/agnostos/main_$label; mkdir -p $R
    t0=$SECONDS
    python3 -m agnostos_mjx.eval --batch 75 --backend $b --resume --quiet --out $R \
      --compare "X-ICM 7B" "$@" 2>&1 | quiet | tail -40 || true
    echo "main job $b $label ($*) wall $((SECONDS - t0)) s" | tee -a $R/wall.txt
    tar -C /tmp/agnostos --exclude='*.mp4' -czf "$OUT/main_$label.tgz" main_$label ;;
esac
