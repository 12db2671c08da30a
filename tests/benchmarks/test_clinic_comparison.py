"""Visits compared on clinic scenes against the back alone: one person run as users run it
(a fresh process), resumed, refused on other code; the other visits' dress."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

from bench_scripts import load_script, run_script


def _run(*args: str) -> Any:
    return run_script("clinic_comparison", *args, timeout=900)


def test_a_person_is_compared_as_a_body_and_as_its_back_alone(tmp_path: Path) -> None:
    out = tmp_path / "cc.jsonl"
    args = ("--first-seed", "45", "--people", "1", "--out", str(out))
    done = _run(*args)
    assert done.returncode == 0, done.stderr[-2000:]
    rows = [json.loads(x) for x in out.read_text().splitlines()]
    assert len(rows) == 1 and rows[0]["seed"] == 45 and "error" not in rows[0]
    body, back = rows[0]["body"], rows[0]["back"]
    # person 45 (tuning): arms away at the first visit, hands on the hips at the second; the
    # back unchanged. The arms are not compared, the back shows no change.
    assert body["posture"]["A"] != body["posture"]["E"]
    assert body["maps"]["E"]["rms_mm"] < 0.5
    assert back["maps"]["E"]["rms_mm"] < 0.5
    assert body["maps"]["C"]["error_rms_mm"] < 0.5  # the +3° progression mapped
    # the same pairs with version 1 of the comparison: the arms show as a change
    assert rows[0]["body_v1"]["maps"]["E"]["rms_mm"] > 1.0
    # and with version 3 (hits through holes kept): no such hit on this trunk, the same map
    assert rows[0]["body_v3"]["maps"]["E"]["rms_mm"] == body["maps"]["E"]["rms_mm"]
    assert "| A→E refused |" in done.stdout
    again = _run(*args)  # resumed: nothing left to do, nothing appended
    assert again.returncode == 0, again.stderr[-2000:]
    assert "1 people done, 0 to go" in again.stdout
    assert len(out.read_text().splitlines()) == 1


def test_rows_of_other_code_and_no_people_are_refused(tmp_path: Path) -> None:
    out = tmp_path / "cc.jsonl"
    out.write_text(json.dumps({"seed": 1, "stamp": "analysis.old 0"}) + "\n")
    done = _run("--people", "1", "--out", str(out))
    assert done.returncode == 2
    assert "other analysis or comparison code" in done.stderr
    done = _run("--people", "0", "--out", str(tmp_path / "b.jsonl"))
    assert done.returncode == 2
    assert "--people must be at least 1" in done.stderr


def test_another_visit_keeps_the_back_and_changes_the_dress() -> None:
    cc = load_script("clinic_comparison")
    first = cc.role_body(45, "A")
    assert cc.role_body(45, "D") == first
    other = cc.redress(first, 11)
    assert other.back.curves == first.back.curves
    assert dataclasses.replace(other.back, arm_gap=first.back.arm_gap) == first.back
    assert (other.head_size, other.hair_albedo) == (first.head_size, first.hair_albedo)
    assert other.hair_seed != first.hair_seed
    assert cc.redress(first, 11) == other  # reproducible
    swayed = cc.role_body(45, "E")
    assert swayed.back.curves == first.back.curves and swayed.back != first.back
    grown = cc.role_body(45, "G").back.curves[0]
    assert abs(grown.rotation) == abs(first.back.curves[0].rotation) + 3.0
    assert cc.people(45, 3)[0] == 45 and all(
        cc.role_body(s, "A").back.curves for s in cc.people(45, 3)
    )
