"""The built-in methods as their files declare them (models.declared): found without importing, in rank order,
and a malformed declaration named by its file."""

from __future__ import annotations

import importlib
from pathlib import Path

import pytest

from models.declared import read_declared
from models.registry import BUILTIN_METHODS, DECLARED, fusion_kwargs

FUSION_DIR = Path(__file__).resolve().parents[2] / "models" / "fusion"


def test_the_built_ins_are_what_their_files_declare() -> None:
    assert BUILTIN_METHODS == ("none", "late", "early", "attfuse", "fcooper", "v2vnet", "disconet", "cobevt")
    for m in DECLARED.values():
        if m.bracket:
            continue
        cls = getattr(importlib.import_module(m.module), m.factory)
        # the class carries the same sizes a plugin's class would (models.registry reads either)
        assert cls.preset_kwargs == m.preset_kwargs, m.name
    assert fusion_kwargs("cobevt", "tiny")["blocks"] == 1 and fusion_kwargs("cobevt", "paper")["blocks"] == 3
    assert fusion_kwargs("attfuse", "tiny") == {}
    with pytest.raises(ValueError, match="preset"):
        fusion_kwargs("cobevt", "huge")


def _folder(tmp_path: Path, **files: str) -> Path:
    for name, text in files.items():
        (tmp_path / f"{name}.py").write_text(text)
    return tmp_path


def test_a_new_file_is_a_new_method_in_its_rank(tmp_path: Path) -> None:
    folder = _folder(tmp_path,
                     b='METHOD = {"name": "second", "factory": "Second", "rank": 2}\nimport torch\n',
                     a='METHOD = {"name": "first", "factory": "First", "rank": 1,\n'
                       '          "preset_kwargs": {"tiny": {"k": 3}}}\n',
                     helper="X = 1\n")  # no METHOD: not a method
    got = read_declared(folder, "pkg")
    assert [m.name for m in got] == ["first", "second"]
    assert got[0].target == "pkg.a:First" and got[0].preset_kwargs == {"tiny": {"k": 3}}
    assert got[1].paper_camera_iou is None and got[1].paper_lidar_ap70 is None


@pytest.mark.parametrize(("text", "match"), [
    ('METHOD = {"name": "Bad Name", "factory": "F", "rank": 1}', "no method name"),
    ('METHOD = {"name": "m", "factory": "F"}', "rank must be an integer"),
    ('METHOD = {"name": "m", "rank": 1}', "needs a factory"),
    ('METHOD = {"name": "m", "factory": "F", "rank": 1, "bracket": True}', "only late, early are brackets"),
    ('METHOD = {"name": "m", "factory": "F", "rank": 1, "size": 3}', "unknown key 'size'"),
    ('METHOD = {"name": "m", "factory": "F", "rank": 1, "paper": {"camera_iou": (1, 2)}}', "camera_iou"),
    ('METHOD = dict(name="m")', "must be a literal"),
])
def test_a_malformed_declaration_names_its_file(tmp_path: Path, text: str, match: str) -> None:
    folder = _folder(tmp_path, mine=text + "\n")
    with pytest.raises(ValueError, match=match) as e:
        read_declared(folder, "pkg")
    assert "mine.py" in str(e.value)


def test_a_name_or_rank_declared_twice_is_refused(tmp_path: Path) -> None:
    folder = _folder(tmp_path, a='METHOD = {"name": "m", "factory": "F", "rank": 1}\n',
                     b='METHOD = {"name": "m", "factory": "G", "rank": 2}\n')
    with pytest.raises(ValueError, match="name 'm' declared by both pkg.a and pkg.b"):
        read_declared(folder, "pkg")
    (folder / "b.py").write_text('METHOD = {"name": "n", "factory": "G", "rank": 1}\n')
    with pytest.raises(ValueError, match="rank 1"):
        read_declared(folder, "pkg")


def test_the_shipped_fusion_folder_reads(tmp_path: Path) -> None:
    assert tuple(m.name for m in read_declared(FUSION_DIR, "models.fusion")) == BUILTIN_METHODS
