#!/usr/bin/env bash
# Evaluate the shipped zoo on held-out seeds (never used in training or validation): both shipped
# SUMO scenarios, the channel as shipped (27 Mbps: feature messages one frame late) and the ideal
# channel (no bandwidth limit), 200 frames, all methods. Prints the table of docs/results.md.
#   scripts/eval_zoo.sh [OUT_DIR] [SEEDS...]      (defaults: runs/eval, seeds 0 1)
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-runs/eval}
shift || true
SEEDS=${*:-0 1}
V=${V2VSIM:-v2vsim}
dirs=()
for sc in intersection t_junction; do
  for seed in $SEEDS; do
    $V run scenarios/$sc.yaml --frames 200 --out "$OUT/${sc}_s${seed}_default" --set seed=$seed --set output.rerun=false
    $V run scenarios/$sc.yaml --frames 200 --out "$OUT/${sc}_s${seed}_ideal" --set seed=$seed \
      --set comm.bandwidth_mbps=null --set output.rerun=false
    dirs+=("$OUT/${sc}_s${seed}_default" "$OUT/${sc}_s${seed}_ideal")
  done
done
python scripts/zoo_table.py "${dirs[@]}"
