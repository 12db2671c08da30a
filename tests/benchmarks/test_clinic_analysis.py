"""The clinical answer on clinic scenes against the back alone: run as users run it (a fresh
process), resumed, refused on other analysis code; its summary on hand-made rows."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from bench_scripts import load_script, run_script


def _run(*args: str) -> Any:
    return run_script("clinic_analysis", *args, timeout=600)


def _module() -> Any:
    return load_script("clinic_analysis")


def test_a_scene_is_analysed_as_a_body_and_as_its_back_alone(tmp_path: Path) -> None:
    out = tmp_path / "ca.jsonl"
    args = ("--first-seed", "100", "--scenes", "1", "--workers", "1", "--out", str(out))
    done = _run(*args)
    assert done.returncode == 0, done.stderr[-2000:]
    rows = [json.loads(x) for x in out.read_text().splitlines()]
    assert sorted(r["kind"] for r in rows) == ["back", "body"]
    assert all("error" not in r and r["seed"] == 100 for r in rows)
    back = next(r for r in rows if r["kind"] == "back")
    # scene 100 (default code, arms away): the back alone finds every landmark within 5 mm
    for name in ("VP", "DL", "DR", "DM", "SP"):
        entry = back["landmarks"][name]
        assert entry["found"], name
        assert sum(e * e for e in entry["error"]) ** 0.5 < 5.0, name
    assert "| body |" in done.stdout and "| back |" in done.stdout
    again = _run(*args)  # resumed: nothing left to do, nothing appended
    assert again.returncode == 0, again.stderr[-2000:]
    assert "2 done, 0 to go" in again.stdout
    assert len(out.read_text().splitlines()) == 2


def test_rows_of_other_analysis_code_and_an_empty_range_are_refused(tmp_path: Path) -> None:
    out = tmp_path / "ca.jsonl"
    out.write_text(json.dumps({"seed": 1, "kind": "body", "stamp": "analysis.old 0"}) + "\n")
    done = _run("--scenes", "1", "--out", str(out))
    assert done.returncode == 2
    assert "other analysis code" in done.stderr
    done = _run("--scenes", "0", "--out", str(tmp_path / "b.jsonl"))
    assert done.returncode == 2
    assert "--scenes must be at least 1" in done.stderr


def _row(seed: int, kind: str, found: dict[str, bool], err: float = 1.0) -> dict[str, Any]:
    marks = {
        n: {
            "edge_px": 100.0,
            "found": found.get(n, True),
            "error": [err, 0.0, 0.0],
            "reason": None if found.get(n, True) else "ambiguous (why)",
        }
        for n in ("VP", "DL", "DR", "DM", "SP")
    }
    return {"seed": seed, "kind": kind, "reason": "", "landmarks": marks, "midline": None}


def test_summary_counts_what_the_body_loses_against_its_back() -> None:
    ca = _module()
    rows = [
        _row(1, "body", {"DL": False}),
        _row(1, "back", {}),
        _row(2, "body", {}, err=9.0),  # found, but 8 mm worse than the back alone
        _row(2, "back", {}),
        _row(3, "body", {"VP": False}),
        _row(3, "back", {"VP": False}),  # both refuse: not a loss of the body's
        _row(4, "body", {}),  # no back row: the pair is left out
        {"seed": 5, "kind": "body", "error": "ValueError: boom"},
        _row(5, "back", {}),
    ]
    s = ca.summary(rows)
    assert s["scenes"] == 4
    assert s["lost_by_body"]["DL"] == [1] and s["lost_by_body"]["VP"] == []
    assert s["worse_by_body_over_5mm"]["DM"] == [2]
    assert s["body"]["crashed"] == ["5: ValueError: boom"]
    assert s["body"]["DL"] == {
        "in_view": 3, "found": 2, "rms_mm": ((1 + 81) / 2) ** 0.5,
        "p95_mm": s["body"]["DL"]["p95_mm"], "max_mm": 9.0,
    }  # fmt: skip
    assert s["body"]["refusals"] == {"DL: ambiguous": 1, "VP: ambiguous": 1}
    assert "| lost by the body" in ca.markdown(s)
