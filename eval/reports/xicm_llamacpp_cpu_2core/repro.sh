#!/bin/bash
# usage: repro.sh NAME CODE_DIR SERVER_LOG -- eval args...
# Runs `python -m agnostos_mjx.eval ARGS --out $RUNS/NAME` from CODE_DIR (a checkout of the code
# to measure) and writes $RUNS/NAME.meta.json: exit code, wall time, and the generations the
# llama.cpp server computed meanwhile (its "prompt eval time" lines in SERVER_LOG).
# RUNS (default /work/runs) and PYTHON (default python) may be set in the environment.
RUNS=${RUNS:-/work/runs}; PYTHON=${PYTHON:-python}
name=$1; code=$2; slog=$3; shift 4
before=$(grep -c "prompt eval time" "$slog")
t0=$(date +%s.%N)
(cd "$code" && PYTHONDONTWRITEBYTECODE=1 "$PYTHON" -m agnostos_mjx.eval "$@" --out "$RUNS/$name" \
    > "$RUNS/$name.stdout" 2> "$RUNS/$name.stderr")
rc=$?
t1=$(date +%s.%N)
sleep 2
after=$(grep -c "prompt eval time" "$slog")
echo "{\"name\": \"$name\", \"exit\": $rc, \"wall_s\": $(echo "$t1 - $t0" | bc), \"server_generations\": $((after - before))}" \
    | tee "$RUNS/$name.meta.json"
