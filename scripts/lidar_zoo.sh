#!/usr/bin/env bash
# Rebuild the LiDAR model zoo from scratch (README "Training"): record the dataset, then train every
# stage into models/weights/. Each step resumes where it stopped if re-run.
#   scripts/lidar_zoo.sh [DATA_DIR] [WORK_DIR] [ZOO_DIR]
set -euo pipefail
cd "$(dirname "$0")/.."
DATA=${1:-data/lidar}
WORK=${2:-runs/train}
ZOO=${3:-models/weights}
V=${V2VSIM:-v2vsim}
# Both shipped networks, four traffic densities, the scenarios' own CAV placement (they meet from frame 0);
# train / val seeds disjoint from each other and from the evaluation seeds 0-9 (default seed 0 included).
for sc in intersection t_junction; do
  $V dataset scenarios/$sc.yaml --seeds 100-102 --frames 150 --out "$DATA" --split train --set traffic.background_per_hour=600
  $V dataset scenarios/$sc.yaml --seeds 103-105 --frames 150 --out "$DATA" --split train --set traffic.background_per_hour=900
  $V dataset scenarios/$sc.yaml --seeds 106-107 --frames 150 --out "$DATA" --split train --set traffic.background_per_hour=1200
  $V dataset scenarios/$sc.yaml --seeds 108-109 --frames 150 --out "$DATA" --split train --set traffic.background_per_hour=1500
  $V dataset scenarios/$sc.yaml --seeds 90-91 --frames 100 --out "$DATA" --split val
done
# single (encoder + heads) -> cache (its frozen features) -> none/late heads, early, then every intermediate
# method on the same cached features; DiscoNet last (its teacher is early).
for stage in single cache none early cobevt v2vnet attfuse fcooper disconet; do
  $V train --data "$DATA" --stage $stage --out "$ZOO" --work "$WORK" --resume
done
