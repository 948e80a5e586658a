"""Reading a recording back with rerun's own reader, for the tests."""

from __future__ import annotations

from pathlib import Path

from rerun.chunk import RrdReader


class Recording:
    """Every chunk of an .rrd's recording store, by entity path."""

    def __init__(self, path: Path) -> None:
        self.chunks = list(RrdReader(str(path)).store().stream())
        self.entities = {c.entity_path for c in self.chunks}

    def columns(self, entity: str) -> set[str]:
        return {n for c in self.chunks if c.entity_path == entity for n in c.to_record_batch().schema.names}

    def static(self, entity: str, column: str) -> list:
        return [v for c in self.chunks if c.entity_path == entity and c.is_static
                for v in c.to_record_batch().column(column).to_pylist()]

    def rows(self, entity: str, column: str, timeline: str = "frame") -> dict:
        """time on `timeline` -> the column's value (one row per time; a later row wins)."""
        out = {}
        for c in self.chunks:
            if c.entity_path != entity or c.is_static:
                continue
            rb = c.to_record_batch()
            if column not in rb.schema.names:
                continue
            for t, v in zip(rb.column(timeline).to_pylist(), rb.column(column).to_pylist(), strict=True):
                out[t] = v
        return dict(sorted(out.items()))
