"""``rasterserver ingest`` and ``list`` in a subprocess: times keep their zone."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
from installed_cli import run_installed

from rasterserver.config import Settings


#: the installed console script, beside the interpreter running the tests
def run(settings: Settings, *args: str) -> subprocess.CompletedProcess[str]:
    """Run the installed ``rasterserver`` on the test archive and catalogue."""
    return run_installed(
        *args, archive=settings.archive, database_url=settings.database_url, timeout=120
    )


def test_an_offset_given_at_ingest_is_the_instant_listed(
    settings: Settings, tmp_path: Path
) -> None:
    frame = tmp_path / "f.npy"
    np.save(frame, np.random.default_rng(3).integers(0, 256, (16, 16), dtype=np.uint8))
    for args in (("db", "upgrade"), ("patient", "add", "P-1")):
        assert run(settings, *args).returncode == 0
    # refused, not guessed: a time without zone, a number
    for args in (
        ("ingest", str(frame), "--patient", "P-1", "--acquired-at", "2025-03-01T10:15"),
        ("list", "--since", "0.5"),
        ("patient", "add", "P-2", "--birth-date", "0"),
    ):
        done = run(settings, *args)
        assert done.returncode == 2, (args, done.stderr)
        assert "Traceback" not in done.stderr and done.stderr.count("\n") == 1, done.stderr
        assert ("add Z for UTC or the offset" in done.stderr) == (args[0] == "ingest")
    done = run(
        settings,
        "ingest",
        str(frame),
        "--patient",
        "P-1",
        "--acquired-at",
        "2025-03-01T10:15+05:00",
    )
    assert done.returncode == 0, done.stderr
    listed = run(
        settings,
        "list",
        "--json",
        "--since",
        "2025-03-01T05:15Z",
        "--until",
        "2025-03-01T00:16-05:00",
    )
    rows = [json.loads(line) for line in listed.stdout.splitlines()]
    assert [r["acquired_at"] for r in rows] == ["2025-03-01T05:15:00+00:00"]
    assert run(settings, "list", "--json", "--until", "2025-03-01T10:15+05:00").stdout == ""
    # a date alone is 00:00 UTC of that day
    assert len(run(settings, "list", "--since", "2025-03-01").stdout.splitlines()) == 1
