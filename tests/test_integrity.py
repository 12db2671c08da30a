"""The one file classifier of verify (rasterserver.integrity), on its own and on an archive."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rasterserver.archive import Archive, FrameSource
from rasterserver.config import Settings
from rasterserver.integrity import (
    RAW_WORDING,
    Problem,
    classify_files,
    verify_archive,
)


@dataclass(frozen=True)
class Entry:
    path: Path
    kind: str
    uid: str | None


def test_every_state_of_a_file_is_told_apart() -> None:
    files = [
        Entry(Path("a.h5"), "final", "a"),
        Entry(Path("b.h5.tmp-1-2"), "temp", "b"),
        Entry(Path("notes.txt"), "stray", None),
        Entry(Path("c.h5"), "final", "c"),
        Entry(Path("e.h5"), "final", "e"),
    ]
    rows = {"a": "a", "d": "d", "e": "e"}  # d: row without file; c: file without row

    def check(key: str) -> list[Problem]:
        if key == "d":
            return [Problem("missing", key, None, RAW_WORDING.missing)]
        if key == "e":
            return [Problem("corrupt", key, Path("e.h5"), "pixels differ")]
        return []

    seen: list[tuple[int, int]] = []
    problems = classify_files(rows, files, lambda f: f.uid, check, RAW_WORDING,
                              progress=lambda done, total: seen.append((done, total)))
    assert [(p.kind, p.uid) for p in problems] == [
        ("temporary", "b"), ("stray", None), ("missing", "d"), ("corrupt", "e"),
        ("orphaned", "c")]
    assert problems[0].detail == RAW_WORDING.temporary
    assert problems[-1].detail == RAW_WORDING.orphaned
    assert seen == [(1, 4), (2, 4), (3, 4), (4, 4)]


def test_verify_archive_checks_both_stores(settings: Settings) -> None:
    with Archive.create(settings) as archive:
        archive.add_patient("P1")
        acq = archive.ingest([FrameSource(np.zeros((8, 8), np.uint8), name="f")],
                             patient="P1")
        seen: list[tuple[int, int]] = []
        report = verify_archive(archive, progress=lambda d, t: seen.append((d, t)))
        assert report.ok and report.problems == []
        assert (report.raw.acquisitions_checked, report.raw.frames_checked) == (1, 1)
        assert report.derived.frames_checked == 0
        assert seen == [(1, 1)]
        archive.raw.path_for(acq.uid).unlink()
        report = verify_archive(archive)
        assert [(p.kind, p.uid) for p in report.problems] == [("missing", acq.uid)]
        assert not report.ok
