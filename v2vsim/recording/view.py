"""`v2vsim view RUN_DIR`: open a run's recording in the Rerun viewer, print the command where
there is no display, or (`--screenshots DIR --at 0,50,100`) step a headless viewer through
frames and save a PNG of each, for review on a machine without a screen.
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path


class ViewError(Exception):
    """What was wrong, for the command line (exit 2)."""


def find_recording(run: Path) -> Path:
    """RUN_DIR/recording.rrd, or RUN if it is an .rrd file itself."""
    if run.is_file() and run.suffix == ".rrd":
        return run
    if not run.exists():
        raise ViewError(f"{run}: no such run directory")
    rrd = run / "recording.rrd"
    if not rrd.is_file():
        raise ViewError(f"{run}: no recording.rrd in it (was the run made with output.rerun: false?)")
    return rrd


def has_display() -> bool:
    if sys.platform in ("darwin", "win32"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def viewer_command(rrd: Path) -> list[str]:
    return [shutil.which("rerun") or "rerun", str(rrd)]


def open_viewer(rrd: Path) -> int:
    """Start the viewer on `rrd` and wait for it; without a display, say how to look instead."""
    cmd = viewer_command(rrd)
    if not has_display():
        print("No display here. Open the recording with:\n"
              f"  rerun {rrd}\n"
              "on a machine with a screen, or serve it to a browser from here:\n"
              f"  rerun {rrd} --serve-web\n"
              "or take screenshots at some frames:\n"
              f"  v2vsim view {rrd.parent} --screenshots {rrd.parent / 'screenshots'} --at 0,50,100")
        return 0
    return subprocess.call(cmd)


def _free_loopback_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def screenshots(rrd: Path, out: Path, frames: list[int], settle_s: float = 2.0) -> list[Path]:
    """A PNG of the whole viewer (default blueprint) at each frame, from a headless viewer.

    Needs a Vulkan driver (a GPU, or Mesa's software lavapipe: `apt-get install mesa-vulkan-drivers`)."""
    from rerun.experimental import ViewerClient

    out.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault("RERUN_ANALYTICS", "0")
    try:
        viewer = ViewerClient.spawn(headless=True, port=_free_loopback_port(), hide_welcome_screen=True)
    except Exception as e:  # noqa: BLE001 - any spawn failure: say what is needed
        raise ViewError(f"could not start a headless Rerun viewer ({e}); it needs a Vulkan driver "
                        "(apt-get install -y mesa-vulkan-drivers)") from e
    shots = []
    try:
        viewer.open(str(rrd.resolve()))
        time.sleep(settle_s)  # let the views lay out and load before the first picture
        for f in frames:
            viewer.set_time("frame", sequence=f, play_state="paused")
            time.sleep(settle_s / 2)
            path = (out / f"frame_{f:04d}.png").resolve()
            viewer.save_screenshot(str(path))
            shots.append(path)
    finally:
        viewer.quit()
    return shots
