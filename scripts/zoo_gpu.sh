#!/usr/bin/env bash
# Train a zoo on a CUDA machine that has no SUMO (docs/training.md): the traffic is recorded
# where SUMO is (`scripts/zoo_data.sh DATA N --traffic-only [FLAGS]`), copied over, sensed here in
# parallel, then every stage trains with --device cuda. Resumable: re-run to continue.
#   scripts/zoo_gpu.sh DATA WORK ZOO ENCODER N "FLAGS" STAGE...
# e.g. scripts/zoo_gpu.sh /tmp/gw/lidar /tmp/gw/train_lidar /tmp/gw/zoo pointpillars 24 "" single cache none
set -euo pipefail
cd "$(dirname "$0")/.."
DATA=$1 WORK=$2 ZOO=$3 ENCODER=$4 N=$5 FLAGS=$6
shift 6
V=${V2VSIM:-v2vsim}
JOBS=${JOBS:-$(nproc)}
WORKERS=${WORKERS:-10}
# shellcheck disable=SC2086
V2VSIM="$V" scripts/zoo_data.sh "$DATA" "$N" --jobs "$JOBS" $FLAGS
# GPU recipe (docs/training.md, "Training on a GPU machine without SUMO"): more data and samples than the CPU recipe, batch 8.
for stage in "$@"; do
  case $stage in
    single) extra="--epochs 8 --samples-per-epoch 3000 --batch 8 --val-every 2" ;;
    cache) extra="" ;;
    early) extra="--epochs 3 --samples-per-epoch 1600 --batch 4 --val-every 3" ;;
    *) extra="--epochs 4 --samples-per-epoch 2400 --batch 8 --val-every 4" ;;
  esac
  # shellcheck disable=SC2086
  $V train --data "$DATA" --stage "$stage" --encoder "$ENCODER" --out "$ZOO" --work "$WORK" --resume \
    --device cuda --threads 8 --workers "$WORKERS" $extra
done
