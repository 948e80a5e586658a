#!/usr/bin/env bash
# Record a zoo's dataset (docs/training.md): both shipped networks, train seeds 100.. at four traffic
# densities (150 frames each), val seeds 90-91 (100 frames each); disjoint from the evaluation seeds 0-89.
#   scripts/zoo_data.sh DATA_DIR [N_TRAIN_SEEDS] [dataset flags...]
# N_TRAIN_SEEDS per network (default 10: seeds 100-109 as 3/3/2/2 at 600/900/1200/1500 veh/h).
# Extra flags go to every `v2vsim dataset` call, e.g. --cameras --set perception.modality=camera, or
# --traffic-only to save only the traffic (sensed later, e.g. on a machine without SUMO), --jobs N.
set -euo pipefail
cd "$(dirname "$0")/.."
DATA=$1
N=${2:-10}
shift $(( $# >= 2 ? 2 : 1 ))
V=${V2VSIM:-v2vsim}
for sc in intersection t_junction; do
  first=100
  g=0
  for density in 600 900 1200 1500; do
    size=$(( N / 4 + (g < N % 4 ? 1 : 0) ))
    if (( size > 0 )); then
      $V dataset scenarios/$sc.yaml --seeds $first-$((first + size - 1)) --frames 150 --out "$DATA" --split train \
        --set traffic.background_per_hour=$density "$@"
    fi
    first=$((first + size))
    g=$((g + 1))
  done
  $V dataset scenarios/$sc.yaml --seeds 90-91 --frames 100 --out "$DATA" --split val "$@"
done
