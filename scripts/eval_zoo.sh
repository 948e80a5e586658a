#!/usr/bin/env bash
# Evaluate the shipped zoo on held-out seeds (never used in training or validation): both shipped SUMO
# scenarios, the channel as shipped (27 Mbps, fusion deadline half a frame) and the ideal channel (no bandwidth
# limit), 200 frames, all methods, with `v2vsim sweep` so that every method's difference to `none` (and CoBEVT's
# to every method) has its paired 95 % bootstrap interval over the seeds (OUT/<scenario>/sweep.md). Resumable.
# Then prints the table of docs/results.md (scripts/zoo_table.py over every run).
#   scripts/eval_zoo.sh [OUT_DIR] [SEEDS]      (defaults: runs/eval, seeds 0-7; SEEDS as A-B or A)
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-runs/eval}
SEEDS=${2:-0-7}
V=${V2VSIM:-v2vsim}
for sc in intersection t_junction; do
  $V sweep scenarios/$sc.yaml --grid comm.bandwidth_mbps=27,null --seeds "$SEEDS" --frames 200 \
    --set output.rerun=false --out "$OUT/$sc"
done
python scripts/zoo_table.py "$OUT"/*/runs/*/seed*
