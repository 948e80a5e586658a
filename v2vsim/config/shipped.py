"""The scenarios shipped with v2vsim: where they are, their names and descriptions, and the one place where a
SCENARIO argument (a path, or the name of a shipped scenario) becomes a YAML file.

A shipped scenario's name is its file's stem (`intersection` -> intersection.yaml). They live in the top-level
scenarios/ folder of a checkout (an editable install runs from it too) and, in a wheel, in the package data folder
v2vsim/scenarios/ (pyproject.toml maps that folder onto scenarios/, networks included). Their paths inside the YAML
(traffic.net, ...) are relative to the YAML file, so they resolve inside whichever of the two holds it.
"""

from __future__ import annotations

import difflib
from pathlib import Path

from v2vsim.config.errors import ConfigError

_PACKAGE = Path(__file__).resolve().parents[1]  # the v2vsim package folder
# Located by file, not imported as a package: a checkout on PYTHONPATH must find its own scenarios, not those of
# another v2vsim that an editable install's import hook maps in.
_PLACES = (
    _PACKAGE / "scenarios",  # a wheel: package data
    _PACKAGE.parent / "scenarios",  # a checkout (also an editable install): the top-level folder
)


def scenarios_dir() -> Path | None:
    """The folder holding the shipped scenario YAMLs; None when this install has none."""
    return next((d for d in _PLACES if d.is_dir() and any(d.glob("*.yaml"))), None)


def shipped_scenarios() -> dict[str, Path]:
    """name -> YAML path of every shipped scenario, sorted by name."""
    folder = scenarios_dir()
    return {} if folder is None else {p.stem: p for p in sorted(folder.glob("*.yaml"))}


def describe(path: Path) -> str:
    """A scenario's one-line description: the first sentence of the comment block that opens its YAML
    (the shipped ones open with one; '' when a file has none)."""
    lines = []
    for line in path.read_text(encoding="utf-8").splitlines():
        if not line.startswith("#"):
            break
        lines.append(line.lstrip("#").strip())
    text = " ".join(w for w in " ".join(lines).split())
    end = text.find(". ")
    return text if end < 0 else text[:end + 1]


def find_scenario(arg: str | Path) -> Path:
    """The YAML file a SCENARIO argument names: an existing file as given (as before names existed), else the
    shipped scenario of that name. ConfigError (one line, the shipped names) when it is neither."""
    path = Path(arg)
    if path.is_file():  # a file wins over a name: `v2vsim run intersection` with ./intersection runs that file
        return path
    shipped = shipped_scenarios()
    if str(arg) in shipped:  # a bare name only: "nets/x" or "x.yaml" that is no file stays an error
        return shipped[str(arg)]
    names = ", ".join(shipped) or "none in this install"
    close = difflib.get_close_matches(path.stem if path.suffix in (".yaml", ".yml") else str(arg), list(shipped), 1)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    raise ConfigError(f"{arg}: scenario file not found, and no shipped scenario has that name{hint}; "
                      f"shipped: {names} (v2vsim scenarios)")
