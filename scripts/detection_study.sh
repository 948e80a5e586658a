#!/bin/bash
# The misbehaviour check's detection study (issue 55; docs/results.md "A lying CAV"): clean runs of every shipped
# scenario and attacked runs of the blind-pullout T-junction, all with `defence.detect: true`, 10 s each; then
# scripts/detection_table.py. Resumable (a finished run is skipped). Calibration used SEED=100, the table SEED=0.
#   SEED=0 OUT=runs/detection bash scripts/detection_study.sh
set -u
cd "$(dirname "$0")/.."
SEED=${SEED:-0}; OUT=${OUT:-runs/detection}/seed$SEED; DUR=${DUR:-10}
mkdir -p "$OUT"
run() {  # name scenario [--set ...]
  local name=$1 scen=$2; shift 2
  [ -f "$OUT/$name/metrics.json" ] && return
  local extra=()
  if grep -q '^control:' "scenarios/$scen.yaml"; then extra=(--set control.method=late); fi
  python -m v2vsim.cli run "scenarios/$scen.yaml" --out "$OUT/$name" --set seed="$SEED" --set defence.detect=true \
    --set duration_s="$DUR" --set output.rerun=false --set 'perception.methods=[none,late,fcooper]' "${extra[@]}" "$@" \
    > "$OUT/$name.log" 2>&1
  echo "$name: $(tail -1 "$OUT/$name.log")"
}
TJ=t_junction_occluded
run lie_scale8 $TJ --set 'misbehaviour=[{cavs: [cav1], kind: scale, factor: 8}]'
run lie_flip $TJ --set 'misbehaviour=[{cavs: [cav1], kind: flip}]'
run lie_zero $TJ --set 'misbehaviour=[{cavs: [cav1], kind: zero}]'
run lie_pose $TJ --set 'misbehaviour=[{cavs: [cav1], kind: pose, shift_m: [6, 0], rotate_deg: 25}]'
run lie_remove $TJ --set 'misbehaviour=[{cavs: [cav1], kind: remove_vehicle}]'
run lie_add $TJ --set 'misbehaviour=[{cavs: [cav1], kind: add_vehicle}]'
run lie_collude_remove $TJ --set 'misbehaviour=[{cavs: [cav1, cav2], kind: remove_vehicle}]'
for scen in t_junction_occluded red_light_runner left_turn_truck blind_corner_stop ramp_merge crossroads_occluded \
            t_junction intersection highway_intersection intersection_camera intersection_mixed; do
  run "clean_$scen" "$scen"
done
python scripts/detection_table.py "$OUT"
