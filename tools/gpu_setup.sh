#!/bin/bash
# Install the carried wheels on the lent GPU machine, in four consecutive calls
# (the warp-lang wheel is split in four parts, one per call; see README "GPU").
#   call k (k = 1..4), carrying .whl .gl .warp/p<k>:   bash tools/gpu_setup.sh <k>
# Then: export PYTHONPATH=/tmp/site:$PWD MUJOCO_GL=egl
set -e
for f in .gl/*.deb; do dpkg -x "$f" /; done
ldconfig
mkdir -p /tmp/w
cp .warp/p"$1"/* /tmp/w/
if [ "$1" = 1 ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target /tmp/site .whl/*.whl
fi
if [ "$1" = 4 ]; then
  whl=/tmp/warp_lang-1.18.0-py3-none-manylinux_2_28_x86_64.whl
  cat /tmp/w/part_* > "$whl"
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site "$whl"
  PYTHONPATH=/tmp/site:$PWD python3 -c "import mujoco, warp, flax, optax, orbax.checkpoint; print('mujoco', mujoco.__version__, 'warp', warp.__version__, 'flax', flax.__version__)"
fi
