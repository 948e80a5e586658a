"""The README is a user's guide that stays true: its verb table lists exactly the CLI's verbs, every
verb it shows answers `--help` on a fresh clone, and every page it links to exists."""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
from pathlib import Path

import pytest

from v2vsim.cli import build_parser

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"


def _section(text: str, title: str) -> str:
    """The body of the `## title` section."""
    m = re.search(rf"^## {re.escape(title)}\n(.*?)(?=^## |\Z)", text, re.M | re.S)
    assert m, f"README has no '## {title}' section"
    return m.group(1)


def readme_verbs() -> list[str]:
    """The verbs in the first column of the README's verb table, in order."""
    rows = [line for line in _section(README.read_text(), "Verbs").splitlines() if line.startswith("| `v2vsim ")]
    return [re.match(r"\| `v2vsim ([a-z]+)", row).group(1) for row in rows]  # type: ignore[union-attr]


def cli_verbs() -> list[str]:
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return list(sub.choices)


def test_verb_table_lists_every_cli_verb_once() -> None:
    verbs = readme_verbs()
    assert len(verbs) == len(set(verbs)), f"a verb is listed twice: {verbs}"
    assert sorted(verbs) == sorted(cli_verbs())


def test_bench_row_lists_every_benchmark() -> None:
    row = next(r for r in _section(README.read_text(), "Verbs").splitlines() if r.startswith("| `v2vsim bench "))
    shown = re.match(r"\| `v2vsim bench ([a-z\\|]+)`", row).group(1).split("\\|")  # type: ignore[union-attr]
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    bench = sub.choices["bench"]
    what = next(a for a in bench._actions if a.dest == "what")
    assert sorted(shown) == sorted(what.choices)


@pytest.mark.parametrize("verb", readme_verbs())
def test_every_verb_in_the_readme_answers_help(verb: str) -> None:
    done = subprocess.run([sys.executable, "-m", "v2vsim.cli", verb, "--help"], cwd=REPO,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert f"usage: v2vsim {verb}" in done.stdout


@pytest.mark.parametrize("what", ["sensors", "models", "comm", "run", "env", "placement"])
def test_every_benchmark_answers_help(what: str) -> None:
    done = subprocess.run([sys.executable, "-m", "v2vsim.cli", "bench", what, "--help"], cwd=REPO,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert f"usage: v2vsim bench {what}" in done.stdout


def test_linked_pages_exist() -> None:
    for page in [README, *sorted((REPO / "docs").glob("*.md"))]:
        for target in re.findall(r"\]\(([^)#]+)(?:#[^)]*)?\)", page.read_text()):
            if "://" not in target:
                assert (page.parent / target).exists(), f"{page.relative_to(REPO)} links to missing {target}"


def test_readme_stays_a_guide() -> None:
    assert len(README.read_text().splitlines()) <= 250
