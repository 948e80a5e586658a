"""Procedurally generated towns (issue 65): one seed -> a SUMO network, its buildings and a scenario YAML.

plan.py draws what a seed decides, roads.py builds the roads with SUMO's netconvert, buildings.py lays buildings
along the blocks, write.py puts one town on disk, sheet.py draws a contact sheet; `generate_towns` is the verb.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import TextIO

from v2vsim.towns.write import TownFiles, write_town

__all__ = ["TownFiles", "generate_towns", "write_town"]


def check_town(files: TownFiles) -> None:
    """Load the town's scenario and reset its traffic once (placement, warm-up, CAVs at frame 0): a town that
    `v2vsim run` could not start fails here, with the town named."""
    from v2vsim.config import load_scenario
    from v2vsim.traffic import make_backend

    backend = make_backend(load_scenario(str(files.scenario)))
    try:
        backend.reset()
    except Exception as e:
        raise RuntimeError(f"{files.scenario}: the generated town does not start: {e}") from e
    finally:
        backend.close()


def generate_towns(seeds: list[int], out: Path, sheet: bool = True, check: bool = True,
                   log: TextIO = sys.stderr) -> list[TownFiles]:
    """Write the towns of `seeds` into `out` (one folder each; an existing town is written again, identically),
    check that each starts, and draw `out/contact_sheet.png` of the first twelve."""
    made = []
    for i, seed in enumerate(seeds):
        files = write_town(seed, out)
        if check:
            check_town(files)
        made.append(files)
        print(f"\rtowns {i + 1}/{len(seeds)}: {files.name} ({files.n_buildings} buildings)   ", end="", file=log,
              flush=True)
    print(file=log)
    if sheet and made:
        from v2vsim.towns.sheet import contact_sheet

        contact_sheet([f.scenario for f in made], out / "contact_sheet.png")
    return made
