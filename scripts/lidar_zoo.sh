#!/usr/bin/env bash
# Rebuild the LiDAR model zoo from scratch (docs/training.md): record the dataset, then train every
# stage into ZOO_DIR (default models/weights/). Each step resumes where it stopped if re-run.
#   scripts/lidar_zoo.sh [DATA_DIR] [WORK_DIR] [ZOO_DIR]     (WIRE_RATIOS="1 16 32 64": CoBEVT on the other wires)
# The grid is the tiny preset's (64 x 64, 1.56 m cells); ZOO_DIR must not hold a zoo of another grid.
# BF16=0 trains every stage in float32 (default where the CPU has native bfloat16: bfloat16 autocast for `none` and
# the fusion methods but CoBEVT; float32 elsewhere).
set -euo pipefail
cd "$(dirname "$0")/.."
DATA=${1:-data/lidar}
WORK=${2:-runs/train}
ZOO=${3:-models/weights}
V=${V2VSIM:-v2vsim}
# bfloat16 only where the CPU computes it natively (AMX or AVX-512 BF16): emulated on an AVX2-only CPU it ran a fusion
# stage ~100x slower than float32
BF16=${BF16:-$(python -c "from v2vsim.perception.precision import native_bf16; print(int(native_bf16()))")}
# SKIP_DATA=1: DATA is recorded already (scripts/towns_zoo.sh records the generated-town dataset first)
[ "${SKIP_DATA:-0}" = 1 ] || scripts/zoo_data.sh "$DATA" 20 --jobs 2
# single (encoder + heads) -> cache (its frozen features) -> compress (the wire's compressors, ratio 8 = the
# wire) -> none/late heads, early, then every intermediate method on the same cached features through the
# wire; DiscoNet last (its teacher is early). A stage whose checkpoint ZOO holds already is skipped (a resume on a
# fresh machine retrains nothing finished; delete the file to train it again); the cache is re-made when WORK
# lacks it (from the zoo's single.pt).
Z="$ZOO/pointpillars_tiny"
have() { [ -f "$Z/$1" ]; }
have single.pt || $V train --data "$DATA" --stage single --out "$ZOO" --work "$WORK" --resume
[ -f "$WORK/cache/done.txt" ] || $V train --data "$DATA" --stage cache --out "$ZOO" --work "$WORK"
have compressor_r64.pt || $V train --data "$DATA" --stage compress --out "$ZOO" --work "$WORK" --resume
flags=()
[ "$BF16" = 1 ] && flags=(--bf16)
# the shipped zoo's recipe: the encoder stages (single, early) and CoBEVT in float32 (bfloat16 made CoBEVT's
# stage slower here), the other heads and fusion methods in bfloat16
have none.pt || $V train --data "$DATA" --stage none --out "$ZOO" --work "$WORK" --resume "${flags[@]}"
have early.pt || $V train --data "$DATA" --stage early --out "$ZOO" --work "$WORK" --resume
have cobevt.pt || $V train --data "$DATA" --stage cobevt --out "$ZOO" --work "$WORK" --resume
for stage in v2vnet attfuse fcooper disconet; do
  have $stage.pt || $V train --data "$DATA" --stage $stage --out "$ZOO" --work "$WORK" --resume "${flags[@]}"
done
# CoBEVT's learned latency extrapolation (comm.compensation), on top of its checkpoint
have cobevt_extrapolate.pt || $V train --data "$DATA" --stage extrapolate --out "$ZOO" --work "$WORK" --resume
# the compression study's CoBEVT on the other wires (ratio 1 = uncompressed; 8 is the zoo's own wire, above)
for r in ${WIRE_RATIOS:-1 16 32 64}; do
  have cobevt_r$r.pt || $V train --data "$DATA" --stage cobevt --wire-ratio "$r" --out "$ZOO" --work "$WORK" --resume
done
