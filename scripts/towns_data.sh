#!/usr/bin/env bash
# Record the generated-town LiDAR dataset (docs/training.md "The zoo on generated towns"): N_TOWNS training towns
# (seeds 1000..), 12 validation towns (seeds 2000-2011), and the intersection as before (train seeds 100-119 at
# four densities, val 90-91). The held-out test towns (seeds 3000..) and every benchmark network stay out
# (`v2vsim train` refuses a dataset holding a benchmark file: v2vsim/training/held_out.py). Re-run to resume.
#   scripts/towns_data.sh DATA_DIR TOWNS_DIR [N_TOWNS] [FRAMES_PER_TOWN] [dataset flags...]
set -euo pipefail
cd "$(dirname "$0")/.."
DATA=$1
TOWNS=$2
N=${3:-80}
F=${4:-80}
shift $(( $# >= 4 ? 4 : $# ))
V=${V2VSIM:-v2vsim}
last=$((1000 + N - 1))
$V towns --seeds 1000-$last --out "$TOWNS/train"
$V towns --seeds 2000-2011 --out "$TOWNS/val"
for s in $(seq 1000 $last); do
  t=$(printf "town_%04d" "$s")
  $V dataset "$TOWNS/train/$t/$t.yaml" --seeds "$s" --frames "$F" --out "$DATA" --split train "$@"
done
for s in $(seq 2000 2011); do
  t=$(printf "town_%04d" "$s")
  $V dataset "$TOWNS/val/$t/$t.yaml" --seeds "$s" --frames 60 --out "$DATA" --split val "$@"
done
first=100
for density in 600 900 1200 1500; do
  $V dataset scenarios/intersection.yaml --seeds $first-$((first + 4)) --frames 150 --out "$DATA" --split train \
    --set traffic.background_per_hour=$density "$@"
  first=$((first + 5))
done
$V dataset scenarios/intersection.yaml --seeds 90-91 --frames 100 --out "$DATA" --split val "$@"
