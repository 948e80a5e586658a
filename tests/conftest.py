"""Test-wide settings."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
import torch


@pytest.fixture(autouse=True, scope="session")
def _one_torch_thread() -> Iterator[None]:
    """One intra-op thread, as in the agent processes: on 2 shared cores, two OpenMP threads under any
    other load ran ~5x slower."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory: pytest.TempPathFactory):
    """A recorded dataset of the intersection: 4 training frames (seed 700), 2 validation frames (701)."""
    import io

    from v2vsim.data.record import record_dataset

    root = tmp_path_factory.mktemp("dataset")
    scenario = "scenarios/intersection.yaml"
    record_dataset(scenario, [700], 4, root, split="train", log=io.StringIO())
    record_dataset(scenario, [701], 2, root, split="val", log=io.StringIO())
    return root
