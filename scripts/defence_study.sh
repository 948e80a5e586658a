#!/bin/bash
# What the defence buys back in perception (issue 55; docs/results.md "A lying CAV"): the open-loop T-junction,
# every lie told by cav1 from frame 0, each run with the check only (`defence.detect`) and with the defence
# (`defence.exclude`), and the clean run both ways; 10 s, held-out seed 0. Resumable. Then a table of vehicle IoU.
#   SEED=0 OUT=runs/defence bash scripts/defence_study.sh
set -u
cd "$(dirname "$0")/.."
SEED=${SEED:-0}; OUT=${OUT:-runs/defence}/seed$SEED; DUR=${DUR:-10}
SCEN=${SCEN:-scenarios/t_junction.yaml}
mkdir -p "$OUT"
run() {  # name lie-or-empty
  local name=$1 lie=$2 mode
  for mode in detect exclude; do
    [ -f "$OUT/$name.$mode/metrics.json" ] && continue
    local sets=(--set seed="$SEED" --set duration_s="$DUR" --set cavs.count=4 --set output.rerun=false
                --set 'perception.methods=[none,late,fcooper,v2vnet,cobevt]' --set "defence.$mode=true")
    [ -n "$lie" ] && sets+=(--set "misbehaviour=[$lie]")
    python -m v2vsim.cli run "$SCEN" --out "$OUT/$name.$mode" "${sets[@]}" > "$OUT/$name.$mode.log" 2>&1
    echo "$name.$mode: $(tail -1 "$OUT/$name.$mode.log")"
  done
}
run clean ""
run scale8 "{cavs: [cav1], kind: scale, factor: 8}"
run flip "{cavs: [cav1], kind: flip}"
run zero "{cavs: [cav1], kind: zero}"
run pose "{cavs: [cav1], kind: pose, shift_m: [6, 0], rotate_deg: 25}"
run remove "{cavs: [cav1], kind: remove_vehicle, targets: [cav2, cav3]}"
run add "{cavs: [cav1], kind: add_vehicle}"
python - "$OUT" <<'PY'
import json, sys
from pathlib import Path
out = Path(sys.argv[1])
methods = ["none", "late", "fcooper", "v2vnet", "cobevt"]
print("| lie | cav1 flagged | " + " | ".join(f"{m} (check only / defence)" for m in methods) + " |")
print("|---|---|" + "---|" * len(methods))
for name in ["clean", "scale8", "flip", "zero", "pose", "remove", "add"]:
    docs = {}
    for mode in ("detect", "exclude"):
        p = out / f"{name}.{mode}" / "metrics.json"
        if p.is_file():
            docs[mode] = json.loads(p.read_text())
    if len(docs) < 2:
        continue
    c1 = docs["exclude"]["defence"]["senders"].get("cav1", {})
    cells = [f"{docs['detect']['methods'][m]['iou_vehicle']:.3f} / {docs['exclude']['methods'][m]['iou_vehicle']:.3f}"
             for m in methods]
    print(f"| {name} | {c1.get('frames_flagged', 0)} / {c1.get('frames_compared', 0)} | " + " | ".join(cells) + " |")
PY
