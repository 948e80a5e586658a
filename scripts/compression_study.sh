#!/usr/bin/env bash
# The wire-compression study (docs/results.md): `none` and the zoo's CoBEVT on held-out seeds of both junctions at
# every channel compression ratio (1 = uncompressed), on the ideal channel (so that only what compression removes
# differs, not when messages arrive), with `v2vsim sweep`; then the table (ratio x IoU and bytes per message)
# beside the field's figures. Each ratio runs CoBEVT trained on that ratio's wire (`v2vsim train --stage cobevt
# --wire-ratio R`, scripts/lidar_zoo.sh; a ratio without one is refused). Resumable.
#   scripts/compression_study.sh [OUT_DIR] [SEEDS] [RATIOS]   (defaults: runs/compression, 0-3, 1,8,16,32,64)
# METHODS=none,cobevt,v2vnet adds methods (each needs its checkpoints per ratio too); EXTRA_SET="--set K=V" more.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-runs/compression}
SEEDS=${2:-0-3}
RATIOS=${3:-1,8,16,32,64}
V=${V2VSIM:-v2vsim}
for sc in intersection t_junction; do
  $V sweep scenarios/$sc.yaml --grid comm.channel_compression=$RATIOS --seeds "$SEEDS" --frames 200 \
    --methods ${METHODS:-none,cobevt} --set comm.bandwidth_mbps=null --set output.rerun=false ${EXTRA_SET:-} --out "$OUT/$sc"
done
python scripts/compression_table.py "$OUT"/* --plot "$OUT/compression.png"
