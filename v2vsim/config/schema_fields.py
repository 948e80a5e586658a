"""The scenario schema's field helper (`_f`) and the range checks its fields share: each field's metadata says what
is allowed (`allowed`, shown in errors), how to check it (`check`) and whether it names an input file (`path`);
v2vsim.config.validate reads them."""

from __future__ import annotations

import dataclasses
import typing
from dataclasses import field
from typing import Any


def _f(default: Any, allowed: str = "", check: typing.Callable[[Any], bool] | None = None,
       path: str | None = None) -> Any:
    """A dataclass field with a range check. `path`: "file" (must exist) or "file?" (optional)."""
    meta = {"allowed": allowed, "check": check, "path": path}
    if isinstance(default, (list, dict)) or dataclasses.is_dataclass(default):
        return field(default_factory=lambda: default, metadata=meta)
    return field(default=default, metadata=meta)


def _pos(x: float) -> bool:
    return x > 0


def _nonneg(x: float) -> bool:
    return x >= 0


def _prob(x: float) -> bool:
    return 0.0 <= x <= 1.0
