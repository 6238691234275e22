#!/usr/bin/env bash
# Train and evaluate the dynamics diffusion model (default config) on one GPU.
# Usage: train/dynamics_gpu.sh BANK [RUNS]   (rerun the same line to resume)
set -euo pipefail
BANK=${1:?usage: train/dynamics_gpu.sh BANK [RUNS]}
RUNS=${2:-runs}
python -m agnostos_mjx.train.autoencoder --bank "$BANK" --out "$RUNS/ae"
python -m agnostos_mjx.train.dynamics --bank "$BANK" --ae "$RUNS/ae" --out "$RUNS/dyn"
python -m agnostos_mjx.train.evaluate --run "$RUNS/dyn" --bank "$BANK"
