#!/bin/bash
# Install the carried wheels on the lent GPU machine in consecutive calls (the machine
# stays warm 30 s between calls). The tree that travels is ~39 MB (the shipped model and
# memory), so each call carries at most ~20 MB beside it (64 MiB per call):
#   call 0, carrying .whl .gl:            bash tools/gpu_setup.sh 0    mujoco & co, EGL libraries
#   call k = 1..N, carrying .gl .warp/pk: bash tools/gpu_setup.sh k    one 20 MB part of warp-lang
# The last part (N = number of .warp/p* folders made by `split -b 20M`) assembles and installs
# warp-lang. Then: export PYTHONPATH=/tmp/site:$PWD MUJOCO_GL=egl (tools/gpu_run.sh does).
# Native-only work (no warp backend) needs call 0 only.
set -e
for f in .gl/*.deb; do dpkg -x "$f" /; done
ldconfig
if [ "$1" = 0 ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target /tmp/site .whl/*.whl
  exit 0
fi
mkdir -p /tmp/w
cp .warp/p"$1"/* /tmp/w/
if [ "$1" = "${2:-8}" ]; then  # the last part: give N as the 2nd argument if not 8
  whl=/tmp/warp_lang-1.18.0-py3-none-manylinux_2_28_x86_64.whl
  cat /tmp/w/part_* > "$whl"
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site "$whl"
  PYTHONPATH=/tmp/site:$PWD python3 -c "import mujoco, warp, flax, optax, orbax.checkpoint; print('mujoco', mujoco.__version__, 'warp', warp.__version__, 'flax', flax.__version__)"
fi
