#!/usr/bin/env bash
# Rebuild the camera model zoo from scratch (docs/training.md, camera track): record the dataset with
# cameras, then train every SinBEVT stage and LaRa's `none` and `cobevt` into models/weights/. The encoders
# start from the ImageNet EfficientNet-Lite0 of the tiny preset (models/image_backbone.py); a ZOO_DIR whose
# camera zoo has another image backbone is refused (train into a new directory, then replace the old zoo).
# Each step resumes where it stopped if re-run.
#   scripts/camera_zoo.sh [DATA_DIR] [WORK_DIR] [ZOO_DIR]      (N_SEEDS=10: training seeds per network)
set -euo pipefail
cd "$(dirname "$0")/.."
DATA=${1:-data/camera}
WORK=${2:-runs/train_camera}
ZOO=${3:-models/weights}
V=${V2VSIM:-v2vsim}
# "visible" means seen by a camera: the dataset's visibility masks follow the cameras, not the LiDAR.
scripts/zoo_data.sh "$DATA" "${N_SEEDS:-10}" --cameras --set perception.modality=camera --set perception.encoder=sinbevt
# A camera zoo has no `early` stage (early fusion ships LiDAR points); DiscoNet trains without its teacher.
# The single-agent stages run 6 epochs (3 left them short of convergence: docs/training.md, "The camera track"),
# in bfloat16 autocast (the same loss path as float32 side by side, and faster per step: docs/training.md,
# "bfloat16").
$V train --data "$DATA" --encoder sinbevt --stage single --epochs 6 --out "$ZOO" --work "$WORK/sinbevt" --resume --bf16
for stage in cache none cobevt v2vnet attfuse fcooper disconet; do
  $V train --data "$DATA" --encoder sinbevt --stage $stage --out "$ZOO" --work "$WORK/sinbevt" --resume
done
$V train --data "$DATA" --encoder lara --stage single --epochs 6 --out "$ZOO" --work "$WORK/lara" --resume --bf16
for stage in cache none; do
  $V train --data "$DATA" --encoder lara --stage $stage --out "$ZOO" --work "$WORK/lara" --resume
done
# LaRa's CoBEVT on the pretrained encoder's features is not trained out after 3 epochs (validation vehicles
# 0.214 at epoch 2, 0.164 at 3; 0.264 after 6): it trains 6.
$V train --data "$DATA" --encoder lara --stage cobevt --epochs 6 --out "$ZOO" --work "$WORK/lara" --resume
