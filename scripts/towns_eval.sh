#!/usr/bin/env bash
# The old zoo beside the new one, open loop, on worlds neither trained on (issue 65, docs/results.md "The zoo on
# generated towns"): held-out seeds of the two old junctions, every benchmark family's scenario with its cast
# (control off), and held-out generated towns (seeds 3000..). Every method, 150 frames, the default channel; one
# `v2vsim sweep` per scenario and zoo, so each method's difference to `none` has its paired interval over seeds
# (and frames) in OUT/<old|new>/<scenario>/sweep.md. Resumable. ONLY=old or ONLY=new runs one zoo's half (the old
# zoo's can run while the new one trains). SCENARIOS overrides the scenario list. Then the tables (scripts/towns_table.py).
#   scripts/towns_eval.sh OUT_DIR OLD_ZOO NEW_ZOO [SEEDS] [N_TOWNS]     (SEEDS default 0-1, N_TOWNS 10)
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=$1
OLD=$(realpath "$2")
NEW=$(realpath "$3")
SEEDS=${4:-0-1}
NT=${5:-10}
V=${V2VSIM:-v2vsim}
# METHODS overrides the list (a zoo still missing a stage cannot run it: the run refuses an untrained method); a
# method added later runs beside the first sweeps with SUFFIX (OUT/<old|new>SUFFIX/...; towns_table.py counts
# the repeated `none` runs once)
ALL=${METHODS:-"[none, late, early, attfuse, fcooper, v2vnet, disconet, cobevt]"}
sweep() {  # sweep SCENARIO NAME SEEDS: one sweep per zoo (a sweep skips the runs it finished before)
  for label in ${ONLY:-old new}; do
    zoo=$OLD; [ "$label" = new ] && zoo=$NEW
    $V sweep "$1" --grid perception.weights="$zoo" --seeds "$3" --frames 150 --set control=null \
      --set "perception.methods=$ALL" --set output.rerun=false --out "$OUT/$label${SUFFIX:-}/$2"
  done
}
for sc in ${SCENARIOS:-intersection t_junction left_turn_truck crossroads_occluded ramp_merge red_light_runner \
          blind_corner_stop t_junction_occluded}; do
  sweep scenarios/$sc.yaml $sc "$SEEDS"
done
[ -d "$OUT/towns/town_$((3000 + NT - 1))" ] || $V towns --seeds 3000-$((3000 + NT - 1)) --out "$OUT/towns" --no-check
for s in $(seq 3000 $((3000 + NT - 1))); do
  t=$(printf "town_%04d" "$s")
  sweep "$OUT/towns/$t/$t.yaml" "$t" 0
done
[ -n "${ONLY:-}" ] || python scripts/towns_table.py "$OUT" "$OLD" "$NEW"
