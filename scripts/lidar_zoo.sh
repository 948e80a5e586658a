#!/usr/bin/env bash
# Rebuild the LiDAR model zoo from scratch (docs/training.md): record the dataset, then train every
# stage into models/weights/. Each step resumes where it stopped if re-run.
#   scripts/lidar_zoo.sh [DATA_DIR] [WORK_DIR] [ZOO_DIR]
set -euo pipefail
cd "$(dirname "$0")/.."
DATA=${1:-data/lidar}
WORK=${2:-runs/train}
ZOO=${3:-models/weights}
V=${V2VSIM:-v2vsim}
scripts/zoo_data.sh "$DATA" 10
# single (encoder + heads) -> cache (its frozen features) -> none/late heads, early, then every intermediate
# method on the same cached features; DiscoNet last (its teacher is early).
for stage in single cache none early cobevt v2vnet attfuse fcooper disconet; do
  $V train --data "$DATA" --stage $stage --out "$ZOO" --work "$WORK" --resume
done
