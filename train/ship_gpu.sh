#!/usr/bin/env bash
# Train, check and export the shipped dynamics model on one GPU, in resumable stages that
# each fit a 10-minute call (rerun a stage to resume it).
#   train/ship_gpu.sh train BANK RUNS SECONDS   autoencoder, then the dynamics model until SECONDS
#   train/ship_gpu.sh finish BANK RUNS OUT      dynamics to its last step, evaluate, export,
#                                               evaluate the export, build the seen memory
set -euo pipefail
PRESET=${PRESET:-default}  # PRESET=quick: a CPU smoke run of the same stages
stage=${1:?usage: train/ship_gpu.sh train|finish BANK RUNS ...}
BANK=${2:?BANK}
RUNS=${3:?RUNS}
mkdir -p "$RUNS"
t0=$SECONDS
case "$stage" in
  train)
    python -m agnostos_mjx.train.autoencoder --preset "$PRESET" --bank "$BANK" --out "$RUNS/ae" --no-progress
    echo "autoencoder done at $((SECONDS - t0)) s"
    left=$(( ${4:?SECONDS} - (SECONDS - t0) ))
    timeout "$left" python -m agnostos_mjx.train.dynamics --preset "$PRESET" --bank "$BANK" \
      --ae "$RUNS/ae" --out "$RUNS/dyn" --no-progress || echo "dynamics stopped at $((SECONDS - t0)) s (resumable)"
    ;;
  finish)
    OUT=${4:?OUT}
    mkdir -p "$OUT"
    python -m agnostos_mjx.train.dynamics --preset "$PRESET" --bank "$BANK" --ae "$RUNS/ae" \
      --out "$RUNS/dyn" --no-progress ${STEPS:+--steps "$STEPS"}
    echo "dynamics done at $((SECONDS - t0)) s"
    python -m agnostos_mjx.train.evaluate --run "$RUNS/dyn" --bank "$BANK"
    echo "evaluate done at $((SECONDS - t0)) s"
    python -m agnostos_mjx.train.export --run "$RUNS/dyn" --out "$RUNS/export"
    python -m agnostos_mjx.train.evaluate --run "$RUNS/export" --bank "$BANK" --json "$RUNS/eval_export.json"
    python -m agnostos_mjx.xicm.build_memory --bank "$BANK" --checkpoint "$RUNS/export" --out "$RUNS/seen_memory.npz"
    echo "export and memory done at $((SECONDS - t0)) s"
    mkdir -p "$RUNS/report"
    cp "$RUNS/export/export.json" "$RUNS/eval_export.json" "$RUNS/report/"
    cp "$RUNS/dyn/eval.json" "$RUNS/report/eval.json"
    cp "$RUNS/dyn/log.jsonl" "$RUNS/report/dyn_log.jsonl"
    cp "$RUNS/ae/log.jsonl" "$RUNS/report/ae_log.jsonl"
    cp "$(ls -d "$RUNS"/dyn/samples/*.png | tail -1)" "$RUNS/report/dyn_samples.png"
    cp "$(ls -d "$RUNS"/ae/samples/*.png | tail -1)" "$RUNS/report/ae_samples.png"
    tar -C "$RUNS" -czf "$OUT/report.tgz" report
    split -b 15M "$RUNS/export/params.npz" "$OUT/params.npz.part-"
    split -b 15M "$RUNS/seen_memory.npz" "$OUT/seen_memory.npz.part-"
    ;;
esac
