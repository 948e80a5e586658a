#!/usr/bin/env bash
# Where the old zoo's gap on the benchmark's networks comes from (issue 65, docs/results.md "Where the gap came
# from"): each family's scenario open loop with one factor taken away at a time (its light traffic made as dense
# as the training data's middle, its buildings, its standing truck, its vans and trucks), then all of them (what is
# left is the network's geometry and the cast), beside the intersection the zoo was trained on. Held-out seeds,
# 150 frames, none / CoBEVT / V2VNet. Resumable (a run with its metrics.json is skipped).
#   scripts/gap_study.sh OUT_DIR [WEIGHTS] [SEEDS]      (WEIGHTS default models/weights; SEEDS default "0 1")
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=$1
W=$(realpath "${2:-models/weights}")  # absolute: a relative weights path resolves against the scenario
SEEDS=${3:-0 1}
V=${V2VSIM:-v2vsim}
run() {  # run NAME SCENARIO VARIANT SEED [--set ...]
  local name=$1 sc=$2 variant=$3 seed=$4
  shift 4
  local dir="$OUT/$name/$variant/seed$seed"
  [ -f "$dir/metrics.json" ] && return 0
  $V run "$sc" --frames 150 --methods none,cobevt,v2vnet --out "$dir" --set control=null --set seed="$seed" \
    --set output.rerun=false --set perception.weights="$W" "$@" > "$dir.log" 2>&1 || echo "failed: $dir"
}
mkdir -p "$OUT"
for seed in $SEEDS; do
  run intersection scenarios/intersection.yaml as_is "$seed"
  for fam in left_turn_truck crossroads_occluded ramp_merge; do
    sc=scenarios/$fam.yaml
    mkdir -p "$OUT/$fam"/{as_is,dense,no_buildings,no_standing,cars_only,stripped}
    run $fam $sc as_is "$seed"
    run $fam $sc dense "$seed" --set traffic.background_per_hour=900
    run $fam $sc no_buildings "$seed" --set traffic.buildings=null
    [ $fam = left_turn_truck ] && run $fam $sc no_standing "$seed" --set "traffic.standing=[]"
    run $fam $sc cars_only "$seed" --set traffic.vehicle_mix.van=0 --set traffic.vehicle_mix.truck=0
    run $fam $sc stripped "$seed" --set traffic.background_per_hour=900 --set traffic.buildings=null \
      --set "traffic.standing=[]" --set traffic.vehicle_mix.van=0 --set traffic.vehicle_mix.truck=0
  done
done
python scripts/gap_table.py "$OUT"
