"""A scene-by-scene benchmark run resumes only with the stages it was started with."""

from __future__ import annotations

import json
from pathlib import Path
from types import ModuleType

import pytest
from bench_scripts import load_script


def _resume() -> ModuleType:
    return load_script("_resume", "benchmarks_resume_for_tests")


def test_rows_of_the_same_stages_are_skipped_others_refused(tmp_path: Path) -> None:
    resume = _resume()
    stamp = resume.chain_stamp(None)
    assert stamp["params"] == {} and stamp["plugins"]["numbers"].startswith("numbers.code-window")
    other = resume.chain_stamp({"numbers": {"end_dim": 0}})
    out = tmp_path / "run.jsonl"
    assert resume.done_seeds(out, stamp) == set()  # a new run
    out.write_text("".join(json.dumps({"seed": s, "stamp": stamp}) + "\n" for s in (3, 4)) + "\n")
    assert resume.done_seeds(out, stamp) == {3, 4}
    with pytest.raises(SystemExit, match="other stages"):
        resume.done_seeds(out, other)
    # a row written before rows carried their stages: which ones is unknown
    out.write_text(json.dumps({"seed": 5}) + "\n")
    with pytest.raises(SystemExit, match="give another --out"):
        resume.done_seeds(out, stamp)
