"""One name of the model registry (models.registry): a `Registration` (what it points at, where it comes from,
why it cannot be used), the rules a fusion method's name follows, and `PluginError`, raised for a fusion method
from outside the built-ins that cannot be used.

Imports no torch: the registry, the entry-point scan (models.entry_points) and the fusion contract check
(models.fusion.contract) all import this module, and the command line and the scenario checks stay light.
"""

from __future__ import annotations

import importlib.metadata
import re
from dataclasses import dataclass
from typing import Any

FUSION_GROUP = "v2vsim.fusion"  # the entry-point group of fusion plugins (models.entry_points)
BRACKETS = ("late", "early")  # methods around the single-agent model, no fusion module of their own
# A plugin's name goes into --methods lists, YAML lists, checkpoint file names (NAME.pt) and --stage.
METHOD_NAME = re.compile(r"[a-z][a-z0-9_]{0,31}")
# Names taken elsewhere: `v2vsim train --stage` values that are no method, and the zoo's "encoder" pseudo-method.
RESERVED = ("all", "single", "cache", "compress", "extrapolate", "encoder")

BUILTIN, ENTRY_POINT, REGISTERED = "built-in", "entry point", "registered"


class PluginError(ValueError):
    """A fusion method registered from outside the built-ins that cannot be used: it cannot be imported, breaks
    the fusion contract, or its name is taken. The message (one line) names it, where it comes from and why."""


@dataclass
class Registration:
    """One name of the registry: what it points at, where it comes from, and (once loaded) its factory or why
    it cannot be used."""

    name: str
    kind: str  # "fusion" | "encoder"
    target: str  # "module:attribute"
    origin: str  # BUILTIN | ENTRY_POINT | REGISTERED
    modality: str | None = None  # encoders
    dist: str | None = None  # the distribution an entry point comes from: "NAME VERSION"
    entry_point: importlib.metadata.EntryPoint | None = None
    loaded: Any = None
    error: str | None = None  # the PluginError message, once it is known to be broken

    @property
    def builtin(self) -> bool:
        return self.origin == BUILTIN

    def where(self) -> str:
        if self.origin == ENTRY_POINT:
            return f"entry point {self.name} = {self.target} in group {FUSION_GROUP} of distribution {self.dist}"
        if self.origin == REGISTERED:
            return f"registered in-process: {self.target}"
        return f"built-in {self.target}"

    def source(self) -> str:
        """Where it comes from, short (the `v2vsim models` column)."""
        if self.origin == ENTRY_POINT:
            return f"plugin {self.dist}"
        return self.origin
