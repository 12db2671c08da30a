"""Kill a real ingesting process between its durable steps; the archive stays explainable.

Invariant after any crash: no catalogue row without its complete file, and every leftover
file is reported by ``verify`` with an explanation (temporary or orphaned).
"""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from rasterserver.archive import Archive
from rasterserver.config import Settings

SCRIPT = textwrap.dedent(
    """
    import os, sys
    from pathlib import Path
    from rasterserver.archive import Archive, FrameSource
    from rasterserver.config import Settings

    archive_dir, url, frame, step = sys.argv[1:5]

    def hook(name):
        if name == step:
            os._exit(137)  # as abrupt as SIGKILL: no cleanup, no flush

    archive = Archive(Settings(archive=Path(archive_dir), database_url=url), crash_hook=hook)
    archive.ingest([FrameSource(Path(frame)), FrameSource(Path(frame))], patient="P001")
    print("finished without crashing")
    """
)


@pytest.mark.parametrize(
    ("step", "expected"),
    [
        ("temp-written", {"temporary"}),
        ("fsynced", {"temporary"}),
        ("renamed", {"orphaned"}),
        ("committed", set()),
    ],
)
def test_crash_between_steps_leaves_no_row_without_file(
    settings: Settings, tmp_path: Path, step: str, expected: set[str]
) -> None:
    with Archive.create(settings) as archive:
        archive.add_patient("P001")
    frame = tmp_path / "frame.npy"
    np.save(frame, np.random.default_rng(7).integers(0, 256, (604, 576), dtype=np.uint8))
    done = subprocess.run(
        [
            sys.executable,
            "-c",
            SCRIPT,
            str(settings.archive),
            settings.database_url,
            str(frame),
            step,
        ],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert done.returncode == 137, done.stderr
    with Archive(settings) as archive:
        rows = archive.acquisitions()
        report = archive.verify()
        for acq in rows:  # every row's file is complete and matches
            assert archive.raw.check_file(acq.uid, {f.index: f.sha256 for f in acq.frames}).ok
        assert {p.kind for p in report.problems} == expected
        assert all(p.detail for p in report.problems)
        assert len(rows) == (1 if step == "committed" else 0)
