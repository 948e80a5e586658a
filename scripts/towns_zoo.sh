#!/usr/bin/env bash
# The LiDAR zoo on generated towns (docs/training.md "The zoo on generated towns"): record the dataset of 80
# generated training towns, 12 validation towns and the intersection (scripts/towns_data.sh; no benchmark network),
# then every stage of scripts/lidar_zoo.sh into ZOO_DIR. Each step resumes where it stopped if re-run.
#   scripts/towns_zoo.sh [DATA_DIR] [TOWNS_DIR] [WORK_DIR] [ZOO_DIR]
set -euo pipefail
cd "$(dirname "$0")/.."
DATA=${1:-data/towns_lidar}
TOWNS=${2:-data/towns}
WORK=${3:-runs/train_towns}
ZOO=${4:-models/candidates/towns_lidar}
scripts/towns_data.sh "$DATA" "$TOWNS" 80 80 --jobs 2
SKIP_DATA=1 scripts/lidar_zoo.sh "$DATA" "$WORK" "$ZOO"
