#!/usr/bin/env bash
# Rebuild the LiDAR model zoo from scratch (README "Training"): record the dataset, then train every
# stage into models/weights/. Each step resumes where it stopped if re-run.
#   scripts/lidar_zoo.sh [DATA_DIR] [WORK_DIR]
set -euo pipefail
cd "$(dirname "$0")/.."
DATA=${1:-data/lidar}
WORK=${2:-runs/train}
V=${V2VSIM:-v2vsim}
# Both shipped networks, three traffic densities; train / val seeds disjoint from each other and from
# the evaluation seeds 0-9 (the scenarios' default seed 0 included).
for sc in intersection t_junction; do
  $V dataset scenarios/$sc.yaml --seeds 100-102 --frames 150 --out "$DATA" --split train --set traffic.background_per_hour=600
  $V dataset scenarios/$sc.yaml --seeds 103-105 --frames 150 --out "$DATA" --split train --set traffic.background_per_hour=900
  $V dataset scenarios/$sc.yaml --seeds 106-107 --frames 150 --out "$DATA" --split train --set traffic.background_per_hour=1500
  $V dataset scenarios/$sc.yaml --seeds 90-91 --frames 100 --out "$DATA" --split val --set traffic.background_per_hour=1200
done
for stage in single cache early attfuse fcooper v2vnet cobevt disconet; do
  $V train --data "$DATA" --stage $stage --out models/weights --work "$WORK" --resume
done
