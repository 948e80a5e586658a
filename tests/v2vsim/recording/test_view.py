"""What `v2vsim view` checks before it starts a viewer: a Vulkan loader and driver (v2vsim.recording.view)."""

from __future__ import annotations

from pathlib import Path

from v2vsim.recording.view import vulkan_missing


def _icd(folder: Path) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    f = folder / "lvp_icd.x86_64.json"
    f.write_text('{"ICD": {"library_path": "libvulkan_lvp.so"}}')
    return f


def test_a_machine_without_the_vulkan_loader_is_told_so(tmp_path: Path) -> None:
    _icd(tmp_path / "icd.d")
    why = vulkan_missing({}, [str(tmp_path / "icd.d")], loader=lambda: False)
    assert why == "there is no Vulkan loader (libvulkan.so.1)"


def test_a_machine_without_a_driver_is_told_where_none_was_found(tmp_path: Path) -> None:
    empty = tmp_path / "icd.d"
    empty.mkdir()
    why = vulkan_missing({}, [str(empty), str(tmp_path / "absent")], loader=lambda: True)
    assert why == f"there is no Vulkan driver (no ICD file in {empty}, {tmp_path / 'absent'})"


def test_a_driver_in_a_system_folder_or_the_xdg_data_dirs_is_found(tmp_path: Path) -> None:
    _icd(tmp_path / "sys" / "icd.d")
    assert vulkan_missing({}, [str(tmp_path / "sys" / "icd.d")], loader=lambda: True) is None
    _icd(tmp_path / "data" / "vulkan" / "icd.d")
    assert vulkan_missing({"XDG_DATA_DIRS": f"/nowhere:{tmp_path / 'data'}"}, [], loader=lambda: True) is None


def test_drivers_named_in_the_environment_are_the_only_ones_looked_at(tmp_path: Path) -> None:
    icd = _icd(tmp_path / "icd.d")
    assert vulkan_missing({"VK_DRIVER_FILES": str(icd)}, [], loader=lambda: True) is None
    # a driver in a system folder does not help when VK_ICD_FILENAMES names only absent ones
    why = vulkan_missing({"VK_ICD_FILENAMES": str(tmp_path / "gone.json")}, [str(tmp_path / "icd.d")],
                         loader=lambda: True)
    assert why is not None and "gone.json" in why
