#!/usr/bin/env bash
# Evaluate the shipped camera zoo on held-out seeds (never used in training or validation):
# scenarios/intersection_camera.yaml and the T-junction with the same camera settings, SinBEVT (every camera
# method) and LaRa (none, late, cobevt), 200 frames, the channel as shipped (27 Mbps) and the ideal channel (no
# bandwidth limit), with `v2vsim sweep` so that every method's difference to `none` (and CoBEVT's to every
# method) has its paired 95 % bootstrap interval over the seeds (OUT/<scenario>_<encoder>/sweep.md). Resumable.
# Then prints the table of docs/results.md (scripts/zoo_table.py over every run).
#   scripts/eval_camera_zoo.sh [OUT_DIR] [SEEDS]      (defaults: runs/eval_camera, seeds 0-3; SEEDS as A-B or A)
# ENCODERS="sinbevt" (the default: "sinbevt lara") evaluates one encoder; CHANNELS="null" the ideal channel only.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-runs/eval_camera}
SEEDS=${2:-0-3}
V=${V2VSIM:-v2vsim}
for enc in ${ENCODERS:-sinbevt lara}; do
  methods=$([ $enc = lara ] && echo none,late,cobevt || echo none,late,attfuse,fcooper,v2vnet,disconet,cobevt)
  for sc in intersection t_junction; do
    yaml=scenarios/$sc.yaml
    [ $sc = intersection ] && yaml=scenarios/intersection_camera.yaml
    $V sweep $yaml --grid comm.bandwidth_mbps=${CHANNELS:-27,null} --seeds "$SEEDS" --frames 200 \
      --methods $methods --set perception.modality=camera --set perception.encoder=$enc \
      --set output.rerun=false --out "$OUT/${sc}_$enc"
  done
done
python scripts/zoo_table.py "$OUT"/*/runs/*/seed*
