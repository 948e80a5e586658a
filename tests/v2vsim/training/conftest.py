"""Fixtures of the training tests: a camera dataset (cameras, camera visibility) recorded once per session."""

from __future__ import annotations

import io

import pytest

CAMERA = ("perception.modality=camera", "perception.encoder=sinbevt")


@pytest.fixture(scope="session")
def camera_dataset(tmp_path_factory: pytest.TempPathFactory):
    """The intersection with cameras and camera visibility: 2 training frames (seed 710), 2 validation (711)."""
    from v2vsim.data.record import record_dataset

    root = tmp_path_factory.mktemp("camera")
    record_dataset("scenarios/intersection.yaml", [710], 2, root, split="train", overrides=CAMERA, cameras=True,
                   log=io.StringIO())
    record_dataset("scenarios/intersection.yaml", [711], 2, root, split="val", overrides=CAMERA, cameras=True,
                   log=io.StringIO())
    return root
