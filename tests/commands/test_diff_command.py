"""``rasterserver diff`` and ``rasterserver reprocess`` through the installed command."""

from __future__ import annotations

import json
from pathlib import Path

import geometry_truth as gt
import numpy as np
from installed_cli import TRACEBACK, describe, run_installed

from rasterserver.config import Settings, sqlite_url


def test_reprocess_then_diff_name_what_changed(tmp_path: Path) -> None:
    root = tmp_path / "archive"
    settings = Settings(archive=root, database_url=sqlite_url(root))
    image = gt.rendering("back").image
    archive, uids = gt.archive_with_frames(
        settings, {"back": image, "black": np.zeros_like(image)})
    archive.close()

    def cli(*args: str):
        return run_installed(*args, archive=root)

    first = cli("process", "--all", "--no-dask", "-q")
    assert first.returncode == 0, describe(first)
    out = tmp_path / "report"
    again = cli("reprocess", "--all", "--param", "peaks.bias_fraction=0.3", "--no-dask",
                "-o", str(out), "-q")
    assert again.returncode == 0, describe(again)
    assert "1 changed, 1 unchanged" in again.stdout, describe(again)
    assert uids["back"] in again.stdout and uids["black"] not in again.stdout
    assert TRACEBACK not in again.stderr
    data = json.loads((out / "diff.json").read_text())
    assert [a["uid"] for a in data["acquisitions"] if a["status"] == "changed"] == [uids["back"]]
    assert (out / "displacement.png").stat().st_size > 1000

    shown = cli("diff", "default", "peaks.bias_fraction=0.3", uids["black"], "--json")
    assert shown.returncode == 0, describe(shown)
    assert json.loads(shown.stdout)["summary"]["unchanged"] == 1
    none = cli("diff", "default", "peaks.bias_fraction=0.4")
    assert none.returncode == 3 and "process them with each chain" in none.stderr, describe(none)
    missing = cli("diff", "default", "default", "f" * 32)
    assert missing.returncode == 3 and "no acquisition ffff" in missing.stderr, describe(missing)
    bad = cli("diff", "default", "peaks=")
    assert bad.returncode == 2 and "KIND=PLUGIN" in bad.stderr, describe(bad)
    unknown = cli("diff", "default", "peaks=peaks.nope")
    assert unknown.returncode == 3 and TRACEBACK not in unknown.stderr, describe(unknown)
