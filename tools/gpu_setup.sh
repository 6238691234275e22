#!/bin/bash
# Install the carried packages on the lent GPU machine, one call each, back to back (the
# machine is given back after 30 s without a call, and everything installed goes with it).
# The tree that travels is ~40 MB (counted on disk) and a call may carry 64 MiB in all, so
# ~24 MB per call: a call the device refuses as too large leaves that part uninstalled,
# and a run's auto route then falls back to OpenGL:
#   carry .gl .whl  bash tools/gpu_setup.sh base   both of these in one call (22.6 MB: fits
#                                                  while tree + both stay under 64 MiB as
#                                                  counted on disk, `du -c`; on 2026-11-26
#                                                  they came to 64.9: use the two calls below):
#   carry .gl       bash tools/gpu_setup.sh gl     libglvnd (EGL) libraries the image lacks
#   carry .whl      bash tools/gpu_setup.sh whl    mujoco 4.0.0, mujoco-core, mujoco-mjx 3.17.0,
#                                                  trimesh, PyOpenGL (cp312) into /tmp/site
#                   (wheels carried with any earlier call are kept in /tmp/whl, so when even
#                   tree + .whl is too much, carry .gl and .whl/mujoco_core-*.whl with `gl`
#                   and the other wheels with `whl`)
#   carry .warp/pK  bash tools/gpu_setup.sh K [N]  part K of warp-lang (K = 0..N, N = 3 by
#                                                  default); the last part assembles it
#   carry .lrw/s .lrw/a1  bash tools/gpu_setup.sh lerobot1   lerobot-eval's wheels the image lacks,
#   carry .lrw/a2         bash tools/gpu_setup.sh lerobot2   then install them (and /tmp/lerobot-eval)
#                  .lrw/s: pip download --no-deps --only-binary=:all: --python-version 3.12 -d .lrw/s
#                  lerobot==0.6.1 draccus==0.11.6 mergedeep toml gymnasium==1.4.0
#                  farama-notifications termcolor datasets==4.8.5 dill multiprocess pytz;
#                  pip wheel --no-deps -w .lrw/s ./lerobot_env_agnostos; an export in
#                  .lrw/s/agnostos_seen (eval/reports/lerobot_eval_h200); .lrw/a1, .lrw/a2: the
#                  av 15.1.0 wheel (40 MB), split -n 2 -d WHEEL av_part_, one part in each
# Native-only work (no warp backend) needs the first call only. Then
# export PYTHONPATH=/tmp/site:$PWD MUJOCO_GL=egl (tools/gpu_runs.sh and
# train/vla_gpu.sh do).  Making the carried folders (on this machine, all ignored):
#   .whl:     pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp
#             mujoco==4.0.0 mujoco-core==4.0.0 mujoco-mjx==3.17.0 trimesh==5.2.0 PyOpenGL==3.1.9
#   .gl:      apt-get download libegl1 libglvnd0 libgl1 libglx0 libopengl0 libx11-6 libxcb1
#             libxau6 libxdmcp6 libbsd0 libmd0 libx11-data
#   .warp/pK: unzip the warp-lang 1.18.0 wheel, rm -r warp/examples warp/tests
#             warp/bin/warp-clang.so (Warp's CPU compiler: kernels for the GPU go through
#             NVRTC in warp.so, and Warp loads warp-clang only if the file is there),
#             tar cf - . | xz -T2 -6 > warp.tar.xz (82.5 MB), split -n 4 -d warp.tar.xz part_,
#             part_0K into .warp/pK
set -e
gl() {  # only the libraries the image lacks: overwriting its own could break its drivers
  mkdir -p /tmp/gl && for f in .gl/*.deb; do dpkg -x "$f" /tmp/gl; done
  for f in /tmp/gl/usr/lib/x86_64-linux-gnu/*.so*; do
    [ -e "/usr/lib/x86_64-linux-gnu/$(basename "$f")" ] || cp -a "$f" /usr/lib/x86_64-linux-gnu/
  done
  ldconfig
  nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
}
stash() { mkdir -p /tmp/whl && { cp .whl/*.whl /tmp/whl/ 2>/dev/null || true; }; }
whl() {
  stash
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target /tmp/site /tmp/whl/*.whl
  PYTHONPATH=/tmp/site MUJOCO_GL=egl \
    __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json \
    python3 -c "import mujoco, jax; mujoco.Renderer(mujoco.MjModel.from_xml_string('<mujoco/>'), 32, 32); print('mujoco', mujoco.__version__, 'jax', jax.__version__, jax.devices(), 'EGL ok')"
}
case "$1" in
  base) gl && whl ;;
  gl) gl && stash ;;
  whl) whl ;;
  [0-9]*)
    mkdir -p /tmp/w && cp .warp/p"$1"/part_* /tmp/w/
    if [ "$1" = "${2:-3}" ]; then
      cat /tmp/w/part_* | xz -d | tar xf - -C /tmp/site
      PYTHONPATH=/tmp/site python3 -c "import warp, mujoco.mjx; warp.init(); print('warp', warp.__version__, 'CUDA devices', warp.get_cuda_device_count())"
    fi ;;
  lerobot1) mkdir -p /tmp/lrw && cp -r .lrw/s/* .lrw/a1/* /tmp/lrw/ ;;
  lerobot2)
    cp .lrw/a2/* /tmp/lrw/ && cat /tmp/lrw/av_part_* > /tmp/lrw/av-15.1.0-cp312-cp312-manylinux_2_28_x86_64.whl
    rm /tmp/lrw/av_part_*
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site \
      /tmp/lrw/*.whl 2>&1 | grep -v "already exists" || true
    # pip's --target keeps an existing bin/: the command as a script of its own
    printf '#!/bin/sh\nexec python3 -c "import sys; from lerobot.scripts.lerobot_eval import main; sys.argv[0]=\\"lerobot-eval\\"; sys.exit(main())" "$@"\n' > /tmp/lerobot-eval
    chmod +x /tmp/lerobot-eval
    PYTHONPATH=/tmp/site python3 -c "import lerobot, torch, av, datasets; print('lerobot', lerobot.__version__, 'torch', torch.__version__, torch.cuda.is_available())" ;;
  *) echo "usage: bash tools/gpu_setup.sh base|gl|whl|K [N]|lerobot1|lerobot2" >&2; exit 2 ;;
esac
