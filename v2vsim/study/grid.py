"""The sweep's design: `--grid KEY=V1,V2` axes, `--seeds`, the Cartesian product of grid points, the
override set of every run, and the validation of each point before anything runs."""

from __future__ import annotations

import hashlib
import itertools
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from v2vsim.config import ConfigError, check_plugins, load_scenario, parse_override

RESERVED = {"seed": "use --seeds", "output.dir": "the sweep places each run under --out"}
_SLUG_BAD = re.compile(r"[^A-Za-z0-9._=+-]+")


@dataclass(frozen=True)
class Axis:
    """One swept key: its key path, the values as typed (what `--set` gets) and as parsed (YAML scalars)."""

    key: str
    texts: tuple[str, ...]
    values: tuple[Any, ...]

    @property
    def numeric(self) -> bool:
        return all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in self.values)


@dataclass(frozen=True)
class Point:
    """One grid point: a value per axis (index into the axis, the text as typed)."""

    pid: str  # its directory name under runs/
    indices: tuple[int, ...]
    texts: tuple[str, ...]

    def overrides(self, axes: Sequence[Axis]) -> list[str]:
        return [f"{a.key}={t}" for a, t in zip(axes, self.texts, strict=True)]


def split_values(text: str) -> list[str]:
    """'0,0.5,[a, b]' -> ['0', '0.5', '[a, b]']: commas inside brackets, braces or quotes do not split."""
    out, depth, quote, cur = [], 0, "", []
    for ch in text:
        if quote:
            quote = "" if ch == quote else quote
        elif ch in "'\"":
            quote = ch
        elif ch in "[{":
            depth += 1
        elif ch in "]}":
            depth -= 1
        elif ch == "," and depth == 0:
            out.append("".join(cur).strip())
            cur = []
            continue
        cur.append(ch)
    out.append("".join(cur).strip())
    return out


def parse_axis(text: str) -> Axis:
    """'comm.drop.p=0,0.5' -> Axis; each value is parsed as a YAML scalar exactly as `--set` parses it."""
    key, sep, rest = text.partition("=")
    key = key.strip()
    if not sep or not key or not rest.strip():
        raise ConfigError(f"--grid {text}: expected KEY.PATH=V1,V2,...")
    texts = split_values(rest)
    if any(not t for t in texts):
        raise ConfigError(f"--grid {text}: an empty value (two commas in a row or a trailing comma)")
    values = []
    for t in texts:
        try:
            values.append(parse_override(f"{key}={t}")[1])
        except ConfigError as e:
            raise ConfigError(str(e).replace("--set", "--grid", 1)) from None
    if len(set(texts)) != len(texts):
        raise ConfigError(f"--grid {text}: a value is listed twice")
    if key in RESERVED:
        raise ConfigError(f"--grid {text}: {key} cannot be swept here ({RESERVED[key]})")
    return Axis(key, tuple(texts), tuple(values))


def parse_axes(texts: Sequence[str]) -> list[Axis]:
    axes = [parse_axis(t) for t in texts]
    keys = [a.key for a in axes]
    for k in keys:
        if keys.count(k) > 1:
            raise ConfigError(f"--grid {k}: given twice; put every value in one --grid {k}=V1,V2,...")
    return axes


def parse_seeds(text: str) -> list[int]:
    """'A-B' (inclusive) or a single 'A'."""
    m = re.fullmatch(r"\s*(\d+)\s*(?:-\s*(\d+)\s*)?", text)
    if not m:
        raise ConfigError(f"--seeds {text!r}: expected A-B (inclusive) or A, non-negative integers")
    a = int(m.group(1))
    b = int(m.group(2)) if m.group(2) is not None else a
    if b < a:
        raise ConfigError(f"--seeds {text!r}: A-B needs A <= B")
    return list(range(a, b + 1))


def _slug(axes: Sequence[Axis], texts: Sequence[str]) -> str:
    return "_".join(_SLUG_BAD.sub("-", f"{a.key}={t}") for a, t in zip(axes, texts, strict=True))


def points(axes: Sequence[Axis]) -> list[Point]:
    """The Cartesian product of the axes, in --grid order (the last axis varies fastest).

    A point's directory is named by its values (not its position), so that a resumed sweep with values
    added to an axis finds the runs it has; a short hash keeps names distinct and bounded."""
    out = []
    for idx in itertools.product(*(range(len(a.texts)) for a in axes)):
        texts = tuple(a.texts[i] for a, i in zip(axes, idx, strict=True))
        slug = _slug(axes, texts) or "base"
        digest = hashlib.sha1("\0".join(f"{a.key}={t}" for a, t in zip(axes, texts, strict=True)).encode())
        pid = f"{slug[:80]}-{digest.hexdigest()[:6]}" if len(slug) > 80 or _slug_collides(axes, texts) else slug
        out.append(Point(pid, tuple(idx), texts))
    return out


def _slug_collides(axes: Sequence[Axis], texts: Sequence[str]) -> bool:
    """Two values of one axis that read the same once odd characters are replaced (e.g. 'a b' and 'a/b')."""
    for a, t in zip(axes, texts, strict=True):
        mine = _SLUG_BAD.sub("-", t)
        if sum(_SLUG_BAD.sub("-", u) == mine for u in a.texts) > 1:
            return True
    return False


def base_overrides(axes: Sequence[Axis], user: Sequence[str], methods: str | None) -> list[str]:
    """The overrides every run gets besides its grid point and seed: output.rerun=false unless the user
    says otherwise (a recording per run is large), the user's --set, and --methods as `run` spells it."""
    keys = [parse_override(o)[0] for o in user]
    dotted = [".".join(k) for k in keys]
    for d, o in zip(dotted, user, strict=True):
        if d in RESERVED:
            raise ConfigError(f"--set {o}: {d} cannot be set here ({RESERVED[d]})")
        if d in {a.key for a in axes}:
            raise ConfigError(f"--set {o}: {d} is also swept by --grid; give it in one place")
    explicit = any(d in ("output", "output.rerun") for d in dotted) or any(a.key == "output.rerun" for a in axes)
    out = [] if explicit else ["output.rerun=false"]
    out += list(user)
    if methods:
        out.append(f"perception.methods=[{methods}]")
    return out


def validate(scenario: Path, axes: Sequence[Axis], pts: Sequence[Point], base: Sequence[str],
             seeds: Sequence[int]) -> None:
    """Load the scenario with every point's full override set (and the extreme seeds): a bad key or value is
    a ConfigError naming it, before any run starts; so is a fusion plugin it requests that cannot be used."""
    for p in pts:
        for s in sorted({seeds[0], seeds[-1]}):
            try:
                check_plugins(load_scenario(scenario, [f"seed={s}", *p.overrides(axes), *base]))
            except ConfigError as e:
                where = ", ".join(p.overrides(axes))
                raise ConfigError(f"{e}" + (f" (grid point {where})" if where else "")) from None
