"""The built-in methods as their own files declare them: each module of models/fusion/ that is a method holds a
module-level ``METHOD = {...}`` literal, read here with ast, without importing the module (so naming the methods,
checking a scenario or printing `--help` imports no torch). Adding a built-in method is one file there (its class
and its METHOD) plus its test; models.registry registers whatever this finds.

METHOD's keys:
    name            the method's name (models.registration.METHOD_NAME)
    rank            its place in the built-in methods' order (the default `perception.methods`, reports)
    factory         the nn.Module class in that file, called as factory(channels, **preset_kwargs[preset]);
                    absent for a bracket
    bracket         True for `early` / `late`: around the single-agent model, no fusion module of their own
    preset_kwargs   {model preset: {keyword: value}}: the method's sizes per preset (models.presets); a preset it
                    does not name builds with the class's defaults
    paper           the CoBEVT paper's OPV2V figures for it (DESIGN.md "Reference figures"): camera_iou (vehicle,
                    road, lane %) and lidar_ap70, each None where the paper has none
"""

from __future__ import annotations

import ast
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from models.registration import BRACKETS, METHOD_NAME

DECLARATION = "METHOD"
_KEYS = {"name", "rank", "factory", "bracket", "preset_kwargs", "paper"}


@dataclass(frozen=True)
class DeclaredMethod:
    """One built-in method, as its file declares it."""

    name: str
    rank: int
    module: str  # "models.fusion.cobevt"
    factory: str | None  # the class's name in `module`; None for a bracket
    preset_kwargs: Mapping[str, Mapping[str, Any]]
    paper_camera_iou: tuple[float, float, float] | None
    paper_lidar_ap70: float | None

    @property
    def bracket(self) -> bool:
        return self.factory is None

    @property
    def target(self) -> str:
        return f"{self.module}:{self.factory}"


def _literal(path: Path) -> dict | None:
    """The file's top-level METHOD literal, or None when it declares none."""
    tree = ast.parse(path.read_text(), filename=str(path))
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(isinstance(t, ast.Name) and t.id == DECLARATION
                                                for t in node.targets):
            try:
                value = ast.literal_eval(node.value)
            except ValueError:
                raise ValueError(f"{path}:{node.lineno}: {DECLARATION} must be a literal (a dict of str, numbers, "
                                 "tuples, None)") from None
            if not isinstance(value, dict):
                raise ValueError(f"{path}:{node.lineno}: {DECLARATION} must be a dict, not {type(value).__name__}")
            return value
    return None


def _method(path: Path, package: str, d: dict) -> DeclaredMethod:
    where = f"{path}: {DECLARATION}"
    stray = sorted(set(d) - _KEYS)
    if stray:
        raise ValueError(f"{where}: unknown key {stray[0]!r}; allowed: {', '.join(sorted(_KEYS))}")
    name = d.get("name")
    if not isinstance(name, str) or not METHOD_NAME.fullmatch(name):
        raise ValueError(f"{where}: name {name!r} is no method name (lower-case letters, digits, '_')")
    rank = d.get("rank")
    if not isinstance(rank, int) or isinstance(rank, bool):
        raise ValueError(f"{where}: rank must be an integer, got {rank!r}")
    bracket = d.get("bracket", False) is True
    if bracket != (name in BRACKETS):
        raise ValueError(f"{where}: {name!r}: only {', '.join(BRACKETS)} are brackets (models.registration)")
    factory = d.get("factory")
    if bracket == (factory is not None) or (factory is not None and not isinstance(factory, str)):
        raise ValueError(f"{where}: {name!r} needs " + ("no factory (a bracket)" if bracket else
                                                         "a factory: the name of its class in this file"))
    kwargs = d.get("preset_kwargs", {})
    if not isinstance(kwargs, dict) or not all(isinstance(v, dict) for v in kwargs.values()):
        raise ValueError(f"{where}: preset_kwargs must be {{preset: {{keyword: value}}}}")
    paper = d.get("paper", {})
    cam = paper.get("camera_iou")
    if cam is not None and (len(cam) != 3 or not all(isinstance(x, (int, float)) for x in cam)):
        raise ValueError(f"{where}: paper.camera_iou must be (vehicle, road, lane) or None, got {cam!r}")
    return DeclaredMethod(name, rank, f"{package}.{path.stem}", factory, kwargs,
                          None if cam is None else tuple(float(x) for x in cam), paper.get("lidar_ap70"))


def read_declared(folder: Path, package: str) -> tuple[DeclaredMethod, ...]:
    """Every method declared in `folder`'s modules (package `package`), in rank order; ValueError naming the
    file for a malformed declaration, a name declared twice or a rank taken twice."""
    out: list[DeclaredMethod] = []
    for path in sorted(folder.glob("*.py")):
        d = _literal(path)
        if d is not None:
            out.append(_method(path, package, d))
    for key in ("name", "rank"):
        seen: dict[object, str] = {}
        for m in out:
            v = getattr(m, key)
            if v in seen:
                raise ValueError(f"{folder}: {key} {v!r} declared by both {seen[v]} and {m.module}")
            seen[v] = m.module
    return tuple(sorted(out, key=lambda m: m.rank))
