#!/bin/bash
# Install the carried wheels on the lent GPU machine in consecutive calls (the machine
# stays warm 30 s between calls). The tree that travels is ~39 MB (the shipped model and
# memory), so each call carries at most ~20 MB beside it (64 MiB per call):
#   call 0, carrying .whl .gl:            bash tools/gpu_setup.sh 0    mujoco & co, EGL libraries
#   call k = 0..N, carrying .gl .warp/pk: bash tools/gpu_setup.sh k    one 21 MB part of warp-lang
#   (call 0 installs the wheels, then part 0 of warp when .warp/p0 is carried too)
# The last part (N = number of .warp/p* folders made by `split -b 20M`) assembles and installs
# warp-lang. Then: export PYTHONPATH=/tmp/site:$PWD MUJOCO_GL=egl (tools/gpu_run.sh does).
# Native-only work (no warp backend) needs call 0 only.
set -e
for f in .gl/*.deb; do [ -e "$f" ] && dpkg -x "$f" /; done  # .gl is carried in call 0 only
ldconfig
if [ "$1" = 0 ] && [ -d .whl ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target /tmp/site .whl/*.whl
fi
[ -d .warp/p"$1" ] || exit 0
mkdir -p /tmp/w
cp .warp/p"$1"/* /tmp/w/
if [ "$1" = "${2:-4}" ]; then  # the last part: give N as the 2nd argument if not 4
  # The parts are an xz tarball of the unpacked wheel without examples and tests:
  #   cd DIR && unzip warp_lang-1.18.0-*.whl && rm -r warp/examples warp/tests &&
  #   tar cf - . | xz -T2 -6 > warp.tar.xz && split -b 21M -d warp.tar.xz part_
  cat /tmp/w/part_* | xz -d | tar xf - -C /tmp/site
  PYTHONPATH=/tmp/site:$PWD python3 -c "import mujoco, warp, flax, optax, orbax.checkpoint; print('mujoco', mujoco.__version__, 'warp', warp.__version__, 'flax', flax.__version__)"
fi
