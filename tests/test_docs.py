"""The README and docs/ as a newcomer reads them: short, two commands, links that lead
somewhere."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
LINK = re.compile(r"\]\(([^)#\s]+)(#[^)\s]*)?\)")


def test_readme_is_short_with_two_quick_start_commands():
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) < 100
    start = text.index("## Quick start")
    block = text[start:].split("```")[1]
    commands = [line for line in block.splitlines() if line.strip()]
    assert commands == ['python3 -m pip install -e ".[dev]" && skinpipe demo -o demo_out',
                        "python3 -m pytest"]


def test_ci_runs_the_readme_test_command_then_the_slow_tests():
    ci = (ROOT / ".ci" / "run").read_text().splitlines()
    assert "python3 -m pytest" in ci
    assert ci.index("python3 -m pytest") < ci.index("python3 -m pytest -m slow")


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_relative_links_resolve(page: Path):
    missing = []
    for target, _ in LINK.findall(page.read_text()):
        if re.match(r"^[a-z]+:", target):
            continue
        if not (page.parent / target).exists():
            missing.append(target)
    assert not missing, f"{page.name} links to missing {missing}"


def test_benchmarks_page_holds_current_figures_only():
    text = (ROOT / "docs" / "benchmarks.md").read_text()
    assert not re.search(r"(?i)\b(session|superseded|earlier run|before this)\b", text)
    assert len(text.splitlines()) < 250
