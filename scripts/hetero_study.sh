#!/usr/bin/env bash
# The heterogeneous-collaboration study (issue 48, docs/results.md "A mixed fleet"): HEAL's protocol on our data.
# The same held-out seeds of both junctions, the same four CAVs (cav0 the ego; cavs.count 4 on the T-junction too,
# which ships 6), each fleet a sweep of its own:
#   lidar       every CAV LiDAR (PointPillars): the base; its `none` is the LiDAR ego alone
#   l_cam3      LiDAR ego + three camera CAVs (SinBEVT aligned into the LiDAR space)
#   l_lid1_cam2 LiDAR ego + one LiDAR + two camera CAVs (the shipped scenarios/intersection_mixed.yaml fleet)
#   c_lid3      camera ego + three LiDAR CAVs
#   cam_aligned every CAV camera, aligned (its `none` is the camera ego alone)
#   cam_zoo     every CAV camera with the shipped camera zoo (sinbevt_tiny, its own space): the camera track
#   scripts/hetero_study.sh OUT [SEEDS] [FRAMES]      (default seeds 0-3, 100 frames; resumable)
# scripts/hetero_table.py OUT prints the tables.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=$1
SEEDS=${2:-0-3}
FRAMES=${3:-100}
V=${V2VSIM:-v2vsim}
CAM='modality: camera, encoder: sinbevt'
declare -A FLEET=(
  [lidar]="[]"
  [l_cam3]="[{cavs: [cav1, cav2, cav3], $CAM}]"
  [l_lid1_cam2]="[{cavs: [cav2, cav3], $CAM}]"
  [c_lid3]="[{cavs: [cav0], $CAM}]"
  [cam_aligned]="[{cavs: [cav0, cav1, cav2, cav3], $CAM}]"
)
# fleet-major: the first fleets are complete on both junctions before the next one starts
for name in l_cam3 lidar l_lid1_cam2 c_lid3 cam_aligned cam_zoo; do
  for sc in intersection t_junction; do
    if [ "$name" = cam_zoo ]; then
      fleet=(--set perception.modality=camera --set perception.encoder=sinbevt)
    else
      fleet=(--set "cavs.fleet=${FLEET[$name]}")
    fi
    $V sweep scenarios/$sc.yaml --seeds "$SEEDS" --frames "$FRAMES" --no-replay --set output.rerun=false \
      --set cavs.count=4 "${fleet[@]}" --out "$OUT/$sc/$name"
  done
done
