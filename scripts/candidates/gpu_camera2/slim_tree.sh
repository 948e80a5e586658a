#!/usr/bin/env bash
# The device call's travelling tree (tracked + untracked-not-ignored files + carried paths) must stay under 64 MiB;
# the tracked tree alone is ~75 MiB since gpu_camera1's single.pt and the aligned SinBEVT were committed. The call
# needs none of the shipped zoo's big checkpoints, so for the call two of them are taken out of the index and ignored
# (they stay on disk, untouched; nothing is committed), and put back right after:
#   scripts/candidates/gpu_camera2/slim_tree.sh on      # before the call (do not commit while it is on)
#   scripts/candidates/gpu_camera2/slim_tree.sh off     # after the call: index and .git/info/exclude as before
#   scripts/candidates/gpu_camera2/slim_tree.sh size [CARRY...]   # the travelling tree's size, as the tool counts it
set -euo pipefail
cd "$(dirname "$0")/../../.."
DROP=(models/weights/pointpillars_tiny/align_sinbevt.pt models/weights/lara_tiny/single.pt)
MARK="# gpu_camera2 slim_tree.sh: remove with 'slim_tree.sh off'"
EXCL=$(git rev-parse --git-path info/exclude)
case ${1:-size} in
  on)
    grep -qxF "$MARK" "$EXCL" 2>/dev/null && { echo "already on"; exit 0; }
    mkdir -p "$(dirname "$EXCL")"
    git rm -q --cached -- "${DROP[@]}"
    { echo "$MARK"; printf '/%s\n' "${DROP[@]}"; } >>"$EXCL"
    git status --short -- "${DROP[@]}"
    ;;
  off)
    git reset -q -- "${DROP[@]}"
    if [ -f "$EXCL" ]; then
      tmp=$(mktemp)
      grep -vxF -e "$MARK" $(printf -- "-e /%s " "${DROP[@]}") "$EXCL" >"$tmp" || true
      cat "$tmp" >"$EXCL" && rm -f "$tmp"
    fi
    git status --short -- "${DROP[@]}"
    echo "off: index and $EXCL restored"
    ;;
  size)
    shift || true
    python3 - "$@" <<'EOF'
import os, subprocess, sys
files = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], capture_output=True,
                       check=True).stdout.split(b"\0")
tree = sum(os.lstat(f).st_size for f in {f for f in files if f} if os.path.lexists(f))
carry = {}
for c in sys.argv[1:]:
    carry[c] = sum(os.lstat(os.path.join(d, f)).st_size for d, _, fs in os.walk(c) for f in fs) if os.path.isdir(c) \
        else os.lstat(c).st_size
total = tree + sum(carry.values())
print(f"tracked + untracked-not-ignored: {tree / 2**20:.2f} MiB; carried: "
      + ", ".join(f"{c} {v / 2**20:.2f} MiB" for c, v in carry.items())
      + f"; total {total / 2**20:.2f} MiB of 64 MiB" + ("" if total < 64 * 2**20 else "  ** OVER THE LIMIT **"))
EOF
    ;;
  *) echo "usage: $0 on|off|size [CARRY...]" >&2; exit 2 ;;
esac
