#!/usr/bin/env bash
# The closed-loop leaderboard with a given LiDAR zoo (issue 65: the old zoo beside the generated-town one), one
# family more each pass into one resumable benchmark folder (complete runs are reused), so that every pass ends
# with a leaderboard of the families so far and a stopped job loses at most one run.
#   scripts/towns_leaderboard.sh ZOO OUT      e.g. ZOO=/work/lb_tree/models/candidates/towns_lidar OUT=/work/lb_new
# FAMILIES overrides the order (the two that carry the ranking first).
set -euo pipefail
zoo=$1 out=$2
fams=""
for fam in ${FAMILIES:-left_turn_truck blind_corner_stop red_light_runner ramp_merge crossing_paths blind_pullout}; do
  fams="${fams:+$fams,}$fam"
  echo "== $fams $(date -u)"
  v2vsim benchmark --profile leaderboard --families "$fams" --set "perception.weights=$zoo" --out "$out"
done
echo "leaderboard done $(date -u)"
