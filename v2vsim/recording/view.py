"""`v2vsim view RUN_DIR`: open a run's recording in the Rerun viewer, or (`--screenshots DIR --at 0,50,100`) step a
headless viewer through frames and save a PNG of each, for review on a machine without a screen.

The viewer renders with Vulkan, headless too: what is missing (a display, a Vulkan driver, a writable folder) is
found before it starts and said in one line (ViewError, exit 2) instead of the viewer's Rust panic.
"""

from __future__ import annotations

import ctypes
import os
import shutil
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

from v2vsim.config import ConfigError, check_output_dir


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


# Where the Vulkan loader looks for installable client drivers (ICDs) on Linux, besides $XDG_DATA_DIRS/vulkan/icd.d.
VULKAN_ICD_DIRS = ("/etc/vulkan/icd.d", "/usr/local/etc/vulkan/icd.d", "/usr/local/share/vulkan/icd.d",
                   "/usr/share/vulkan/icd.d")
INSTALL_VULKAN = "`apt-get install -y mesa-vulkan-drivers` (Mesa's lavapipe: software rendering, no GPU needed)"


def vulkan_missing(environ: Mapping[str, str] = os.environ, icd_dirs: Sequence[str] = VULKAN_ICD_DIRS,
                   loader: Callable[[], bool] | None = None) -> str | None:
    """Why the Rerun viewer cannot render here, or None (Linux only; elsewhere the platform's own graphics serve).
    The viewer renders with Vulkan (wgpu) even headless; without a loader or a driver it panics with a Rust
    backtrace ("No graphics adapter was found", "Failed to get render context"). `loader`: whether libvulkan loads."""
    if not sys.platform.startswith("linux"):
        return None
    if not (loader or _vulkan_loader_loads)():
        return "there is no Vulkan loader (libvulkan.so.1)"
    listed = [f for v in ("VK_DRIVER_FILES", "VK_ICD_FILENAMES") for f in environ.get(v, "").split(os.pathsep) if f]
    if listed:  # the user named the drivers: the loader looks nowhere else
        return None if any(Path(f).is_file() for f in listed) else (
            f"the Vulkan drivers that VK_DRIVER_FILES / VK_ICD_FILENAMES name do not exist ({', '.join(listed)})")
    data_dirs = environ.get("XDG_DATA_DIRS", "").split(os.pathsep)
    dirs = [*icd_dirs, *(str(Path(d) / "vulkan" / "icd.d") for d in data_dirs if d)]
    if any(Path(d).is_dir() and any(Path(d).glob("*.json")) for d in dirs):
        return None
    return f"there is no Vulkan driver (no ICD file in {', '.join(icd_dirs)})"


def _vulkan_loader_loads() -> bool:
    try:
        ctypes.CDLL("libvulkan.so.1")
    except OSError:
        return False
    return True


def check_viewer_can_render(environ: Mapping[str, str] = os.environ) -> None:
    """ViewError, in one line with what to install, where a viewer started here would panic for want of Vulkan."""
    missing = vulkan_missing(environ)
    if missing is not None:
        raise ViewError(f"the Rerun viewer renders with Vulkan, and here {missing}: install a driver, e.g. "
                        f"{INSTALL_VULKAN}, or open the recording on a machine with a screen (docs/reviewing.md)")


def viewer_command(rrd: Path) -> list[str]:
    return [shutil.which("rerun") or "rerun", str(rrd)]


def open_viewer(rrd: Path) -> int:
    """Start the viewer on `rrd` and wait for it; ViewError (one line: how to look instead, or what to install)
    without a display or without Vulkan."""
    cmd = viewer_command(rrd)
    if not has_display():
        raise ViewError(f"no display here (DISPLAY and WAYLAND_DISPLAY are unset): open it on a machine with a "
                        f"screen (`rerun {rrd}`), serve it to a browser from here (`rerun {rrd} --serve-web`), or "
                        f"take screenshots (`v2vsim view {rrd.parent} --screenshots {rrd.parent / 'screenshots'} "
                        "--at 0,50,100`)")
    check_viewer_can_render()
    return subprocess.call(cmd)


def _free_loopback_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def screenshots(rrd: Path, out: Path, frames: list[int], settle_s: float = 2.0) -> list[Path]:
    """A PNG of the whole viewer (default blueprint) at each frame, from a headless viewer.

    Needs a Vulkan driver (a GPU, or Mesa's software lavapipe: `apt-get install mesa-vulkan-drivers`)."""
    from rerun.experimental import ViewerClient

    try:
        check_output_dir(out, "--screenshots")  # the same check as `run --out`: one line, before the viewer starts
    except ConfigError as e:
        raise ViewError(str(e)) from None
    check_viewer_can_render()
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
