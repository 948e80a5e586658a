#!/usr/bin/env bash
# The LiDAR fusion-grid study (docs/results.md "Choosing the LiDAR grid"): one short common recipe per grid,
# the same data, seeds and schedule, an uncompressed wire, so that only the grid F x F differs.
#   scripts/grid_study.sh DATA OUT "32 64 128" [STAGES]
# Per grid: single (2 x 1400 samples), cache, then each method in STAGES (default: none v2vnet cobevt;
# 1 x 1200 samples each) into OUT/g<F>/zoo, work files under OUT/g<F>/work. Resumable: re-run the same command.
# The validation figures land in each zoo's manifest.json; scripts/grid_table.py OUT prints the table.
set -euo pipefail
cd "$(dirname "$0")/.."
DATA=$1
OUT=$2
GRIDS=${3:-"32 64 128"}
STAGES=${4:-"none v2vnet cobevt"}
V=${V2VSIM:-v2vsim}
for f in $GRIDS; do
  Z="$OUT/g$f/zoo"; W="$OUT/g$f/work"
  common=(--data "$DATA" --out "$Z" --work "$W" --cells "$f" --resume)
  [ -f "$W/single/final.pt" ] || $V train "${common[@]}" --stage single --epochs 2 --samples-per-epoch 1400
  [ -f "$W/cache/encoder.json" ] || $V train "${common[@]}" --stage cache
  for s in $STAGES; do
    [ -f "$W/$s/final.pt" ] || $V train "${common[@]}" --stage "$s" --epochs 1 --samples-per-epoch 1200
  done
done
