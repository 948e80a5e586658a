"""Validating a raw mapping against the schema: types, ranges, unknown keys and input paths (`_Loader`)."""

from __future__ import annotations

import dataclasses
import difflib
import math
import types
import typing
from pathlib import Path
from typing import Any, Literal

from v2vsim.config.errors import ConfigError

# ---- loading ---------------------------------------------------------------------------------


def _type_name(tp: Any) -> str:
    origin = typing.get_origin(tp)
    if origin is Literal:
        return " | ".join(repr(a) for a in typing.get_args(tp))
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_type_name(a) for a in typing.get_args(tp))
    if origin is tuple:
        args = typing.get_args(tp)
        inner = _type_name(args[0]) if args else "value"
        return f"a list of {inner}" + (f" ({len(args)} items)" if args and args[-1] is not Ellipsis else "")
    if dataclasses.is_dataclass(tp):
        return "a mapping"
    return {int: "an integer", float: "a number", str: "a string", bool: "true/false",
            type(None): "null"}.get(tp, str(tp))


class _Loader:
    def __init__(self, source: str, base_dir: Path | None) -> None:
        self.source = source
        self.base_dir = base_dir

    def fail(self, key: str, msg: str) -> typing.NoReturn:
        raise ConfigError(f"{self.source}: {key}: {msg}")

    def value(self, tp: Any, raw: Any, key: str) -> Any:
        origin = typing.get_origin(tp)
        if dataclasses.is_dataclass(tp):
            return self.section(tp, raw, key)
        if origin is Literal:
            if isinstance(raw, bool) and ("on" if raw else "off") in typing.get_args(tp):
                raw = "on" if raw else "off"  # YAML 1.1 reads a bare off/on (and no/yes) as a boolean
            if raw not in typing.get_args(tp):
                hint = difflib.get_close_matches(str(raw), [str(a) for a in typing.get_args(tp)], 1)
                extra = f" (did you mean {hint[0]!r}?)" if hint else ""
                self.fail(key, f"got {raw!r}; allowed: {_type_name(tp)}{extra}")
            return raw
        if origin in (typing.Union, types.UnionType):
            args = typing.get_args(tp)
            if raw is None and type(None) in args:
                return None
            for a in args:
                if dataclasses.is_dataclass(a) and isinstance(raw, dict):
                    return self.value(a, raw, key)  # a mapping is that section: its own errors name the key inside
            errors = []
            for a in args:
                if a is type(None):
                    continue
                try:
                    return self.value(a, raw, key)
                except ConfigError as e:
                    errors.append(e)
            if len(errors) == 1 and dataclasses.is_dataclass(args[0]) and isinstance(raw, dict):
                raise errors[0]  # a section (X | None) given as a mapping: its own error names the inner key
            self.fail(key, f"got {raw!r}; expected {_type_name(tp)}")
        if origin is tuple:
            if not isinstance(raw, (list, tuple)):
                self.fail(key, f"got {raw!r}; expected {_type_name(tp)}")
            args = typing.get_args(tp)
            if args and args[-1] is not Ellipsis:
                if len(raw) != len(args):
                    self.fail(key, f"got {len(raw)} items; expected {_type_name(tp)}")
                pairs = enumerate(zip(args, raw, strict=True))
                return tuple(self.value(a, r, f"{key}[{i}]") for i, (a, r) in pairs)
            return tuple(self.value(args[0], r, f"{key}[{i}]") for i, r in enumerate(raw))
        if tp is bool:
            if not isinstance(raw, bool):
                self.fail(key, f"got {raw!r}; expected true/false")
            return raw
        if tp is int:
            if isinstance(raw, bool) or not isinstance(raw, int):
                self.fail(key, f"got {raw!r}; expected an integer")
            return raw
        if tp is float:
            if isinstance(raw, bool) or not isinstance(raw, (int, float)):
                self.fail(key, f"got {raw!r}; expected a number")
            try:
                value = float(raw)
            except OverflowError:  # an integer beyond any float
                value = math.inf
            if not math.isfinite(value):  # .inf/.nan pass every range check and break frame counts later
                self.fail(key, f"got {raw!r}; expected a finite number")
            return value
        if tp is str:
            if not isinstance(raw, (str, int, float)) or isinstance(raw, bool):
                self.fail(key, f"got {raw!r}; expected a string")
            return str(raw)
        raise TypeError(f"schema type {tp} not handled")  # a bug in the schema, not user input

    def section(self, cls: type, raw: Any, key: str) -> Any:
        if raw is None:
            raw = {}
        if not isinstance(raw, dict):
            self.fail(key or "<top level>", f"got {raw!r}; expected a mapping")
        hints = typing.get_type_hints(cls)
        fields = {f.name: f for f in dataclasses.fields(cls) if not f.metadata.get("internal")}
        for k in raw:
            if k not in fields:
                where = f"{key}.{k}" if key else str(k)
                hint = difflib.get_close_matches(str(k), list(fields), 1)
                extra = f" (did you mean {hint[0]!r}?)" if hint else ""
                self.fail(where, f"unknown key{extra}; allowed here: {', '.join(fields)}")
        out = {}
        for name, f in fields.items():
            where = f"{key}.{name}" if key else name
            if name not in raw:
                continue  # default
            v = self.value(hints[name], raw[name], where)
            check = f.metadata.get("check")
            if v is not None and check is not None and not check(v):
                self.fail(where, f"got {raw[name]!r}; allowed: {f.metadata['allowed']}")
            if v is not None and f.metadata.get("path"):
                v = self.resolve(v, where)
            out[name] = v
        return cls(**out)

    def resolve(self, p: str, key: str) -> str:
        path = Path(p)
        if not path.is_absolute() and self.base_dir is not None:
            path = self.base_dir / path
        if not path.is_file():
            self.fail(key, f"file not found: {path} (paths are relative to the YAML file)")
        return str(path.resolve())
