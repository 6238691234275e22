#!/bin/bash
# The GPU physics-floor measurements of issue 26 on a lent H100 (one stage per device call;
# the machine stays warm 30 s between calls).  Outputs go to $OUT; runs to /tmp/agnostos.
#
# Setup, six consecutive calls (the tree that travels is ~45 MB, so a call carries <= ~20 MB):
#   carry .whl .gl      bash tools/gpu_floor.sh setup     mujoco & co; libglvnd (EGL) if missing
#   carry .warp/pK      bash tools/gpu_floor.sh part K    K = 0..4; part 4 assembles warp-lang
#   (.whl: `pip download` of mujoco 4.0.0, mujoco-core, mujoco-mjx 3.17.0, trimesh for cp312;
#    .warp/pK: `split -b 21M -d` of an xz tarball of the unpacked warp-lang 1.18.0 wheel
#    without warp/examples and warp/tests; .gl: `apt-get download libegl1 libglvnd0 libgl1
#    libglx0 libopengl0 libx11-6 libxcb1 libxau6 libxdmcp6 libbsd0 libmd0 libx11-data`)
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
  setup)
    nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
    python3 --version; nproc
    mkdir -p /tmp/gl && for f in .gl/*.deb; do dpkg -x "$f" /tmp/gl; done
    for f in /tmp/gl/usr/lib/x86_64-linux-gnu/*.so*; do  # only what the image lacks
      [ -e /usr/lib/x86_64-linux-gnu/$(basename "$f") ] || cp -a "$f" /usr/lib/x86_64-linux-gnu/
    done
    ldconfig
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
      --target /tmp/site .whl/*.whl
    python3 -c "import mujoco, jax; print('mujoco', mujoco.__version__, 'jax', jax.__version__, jax.devices())"
    python3 -c "import mujoco; r = mujoco.Renderer(mujoco.MjModel.from_xml_string('<mujoco/>'), 32, 32); print('EGL renderer ok')" 2>&1 | tail -1 ;;
  part)
    mkdir -p /tmp/w && cp .warp/p"$2"/* /tmp/w/
    if [ "$2" = 4 ]; then
      cat /tmp/w/part_* | xz -d | tar xf - -C /tmp/site
      python3 -c "import warp, mujoco.mjx; print('warp', warp.__version__)"
    fi ;;
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
