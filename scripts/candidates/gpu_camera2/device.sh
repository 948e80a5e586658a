#!/usr/bin/env bash
# The one device call (run from the repository root), continuing models/candidates/gpu_camera1:
#   set -o pipefail; export OUT; HARD=545 bash scripts/candidates/gpu_camera2/device.sh 2>&1 | tee $OUT/log.txt
# installs the carried wheels (.whl: shapely) into $SITE, then device_run.py (sensing, cache, none, cobevt, more
# fusion stages while time remains; stops every training HARD seconds after T0 and still copies what finished).
# The cache and later stages never load the ImageNet Lite0 file (only the `single` stage does): no gpucam/site.
# Local test: scripts/candidates/gpu_camera2/local_test.sh.
set -uo pipefail
export T0=${T0:-$(date +%s.%N)}
export PYTHONUNBUFFERED=1
SITE=${SITE:-/tmp/site}
echo "start $(date -u +%FT%TZ) on $(hostname), $(nproc) cores"
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>&1 | head -2
df -h /tmp | tail -1
if [ -z "${SKIP_PIP:-}" ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target "$SITE" .whl/*.whl || exit 3
fi
export PYTHONPATH=$SITE:$PWD${PYTHONPATH:+:$PYTHONPATH}
python3 -c "import torch, numpy, shapely; print('torch', torch.__version__, 'cuda', torch.cuda.is_available(), 'numpy', numpy.__version__, 'shapely', shapely.__version__)"
GPULOG=
if command -v nvidia-smi >/dev/null && [ -n "${OUT:-}" ]; then  # GPU load every 10 s, beside the log
  nvidia-smi --query-gpu=timestamp,utilization.gpu,memory.used --format=csv,noheader -l 10 >"$OUT/gpu.csv" 2>&1 &
  GPULOG=$!
fi
python3 "$(dirname "$0")/device_run.py"
rc=$?
[ -n "$GPULOG" ] && kill "$GPULOG" 2>/dev/null
echo "device_run exit $rc at $(python3 -c "import time, os; print(round(time.time() - float(os.environ['T0']), 1))") s"
ls -la "$OUT"
exit $rc
