#!/usr/bin/env bash
# Evaluate the shipped camera zoo on held-out seeds (never used in training or validation):
# scenarios/intersection_camera.yaml and the T-junction with the same camera settings,
# SinBEVT (every method) and LaRa (none, late, cobevt), 200 frames. Prints the tables of docs/results.md.
#   scripts/eval_camera_zoo.sh [OUT_DIR] [SEEDS...]      (defaults: runs/eval_camera, seeds 0 1)
# CHANNELS="ideal default" (the default: ideal only) adds the channel as shipped (27 Mbps: one frame late);
# ENCODERS="sinbevt" (the default: "sinbevt lara") evaluates one encoder.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-runs/eval_camera}
shift || true
SEEDS=${*:-0 1}
V=${V2VSIM:-v2vsim}
CAMERA=(--set perception.modality=camera --set output.rerun=false)
dirs=()
for enc in ${ENCODERS:-sinbevt lara}; do
  methods=$([ $enc = lara ] && echo none,late,cobevt || echo none,late,attfuse,fcooper,v2vnet,disconet,cobevt)
  for sc in intersection t_junction; do
    yaml=scenarios/$sc.yaml
    [ $sc = intersection ] && yaml=scenarios/intersection_camera.yaml
    for seed in $SEEDS; do
      for channel in ${CHANNELS:-ideal}; do
        bw=$([ "$channel" = ideal ] && echo null || echo 27)
        d="$OUT/${sc}_${enc}_s${seed}_${channel}"
        $V run $yaml --frames 200 --out "$d" --methods $methods --set seed=$seed \
          --set perception.encoder=$enc --set comm.bandwidth_mbps=$bw "${CAMERA[@]}"
        dirs+=("$d")
      done
    done
  done
done
python scripts/zoo_table.py "${dirs[@]}"
