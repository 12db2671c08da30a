"""Benchmark figures written into BENCHMARKS.md keep the dated history of their section."""

from __future__ import annotations

from pathlib import Path

import pytest
from bench_scripts import load_script

BEFORE = """# Benchmarks

## Other

kept as it is

## Back-shape analysis

intro kept

### 2026-11-29: older

old figures

### 2026-11-27: oldest

oldest figures

## Last

last section
"""


@pytest.fixture
def machine_md(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):  # type: ignore[no-untyped-def]
    module = load_script("_machine", "benchmarks_machine_for_tests")
    md = tmp_path / "BENCHMARKS.md"
    md.write_text(BEFORE)
    monkeypatch.setattr(module, "BENCHMARKS_MD", md)
    return module, md


def test_a_new_subsection_goes_first_and_keeps_the_history(machine_md) -> None:  # type: ignore[no-untyped-def]
    module, md = machine_md
    module.write_subsection("Back-shape analysis", "2026-11-30: newest", "new figures")
    text = md.read_text()
    order = [
        text.index(s)
        for s in (
            "intro kept",
            "### 2026-11-30: newest",
            "new figures",
            "### 2026-11-29: older",
            "old figures",
            "oldest figures",
            "## Last",
            "last section",
        )
    ]
    assert order == sorted(order)
    assert "kept as it is" in text and text.count("## Back-shape analysis") == 1


def test_the_same_heading_is_replaced_not_repeated(machine_md) -> None:  # type: ignore[no-untyped-def]
    module, md = machine_md
    module.write_subsection("Back-shape analysis", "2026-11-29: older", "rewritten")
    text = md.read_text()
    assert "old figures" not in text and text.count("### 2026-11-29: older") == 1
    assert text.index("rewritten") < text.index("oldest figures")


def test_a_missing_section_is_appended(machine_md) -> None:  # type: ignore[no-untyped-def]
    module, md = machine_md
    module.write_subsection("New section", "2026-11-30: first", "body")
    text = md.read_text()
    assert text.rstrip().endswith("### 2026-11-30: first\n\nbody")
    assert BEFORE.strip() in text


def test_the_default_heading_is_dated_and_names_the_script() -> None:
    module = load_script("_machine", "benchmarks_machine_for_tests")
    heading = module.subsection_heading(None, "/x/benchmarks/analysis.py")
    assert heading.endswith(": `benchmarks/analysis.py`") and heading[:4].isdigit()
    assert module.subsection_heading("given", "analysis.py") == "given"
