"""``rasterserver prune`` and ``rasterserver stats`` through the installed command."""

from __future__ import annotations

import json
from pathlib import Path

import geometry_truth as gt
import numpy as np
from installed_cli import TRACEBACK, describe, run_installed

from rasterserver.config import Settings, sqlite_url


def test_stats_then_prune_dry_run_then_apply(tmp_path: Path) -> None:
    root = tmp_path / "archive"
    settings = Settings(archive=root, database_url=sqlite_url(root))
    image = gt.rendering("back").image
    archive, _uids = gt.archive_with_frames(settings, {"back": image,
                                                       "black": np.zeros_like(image)})
    archive.close()

    def cli(*args: str):
        done = run_installed(*args, archive=root)
        assert TRACEBACK not in done.stderr, describe(done)
        return done

    for chain in ("peaks.bias_fraction=0.3", None):
        extra = ["--param", chain] if chain else []
        done = cli("reprocess" if chain else "process", "--all", "--until", "mesh", *extra,
                   "--no-dask", "-q", *(["-o", str(tmp_path / "d")] if chain else []))
        assert done.returncode == 0, describe(done)

    stats = cli("stats", "--json")
    assert stats.returncode == 0, describe(stats)
    found = json.loads(stats.stdout)
    assert found["counts"]["acquisitions"] == 2 and found["counts"]["results"] == 2 * 2 * 7
    assert found["files"]["raw frames"]["files"] == 2
    assert [c["acquisitions"] for c in found["chains"]] == [2, 2]
    shown = cli("stats")
    assert "derived mesh" in shown.stdout and "prune would remove" in shown.stdout

    # the newest job ran the default chain: the first chain's results are not kept
    dry = cli("prune")
    assert dry.returncode == 0 and "would remove 14 result(s)" in dry.stdout, describe(dry)
    kept = cli("prune", "--keep", "peaks.bias_fraction=0.3", "--json")
    assert json.loads(kept.stdout)["plan"]["remove"] == 0
    before = found["total_bytes"]
    done = cli("prune", "--apply", "--json")
    assert done.returncode == 0, describe(done)
    report = json.loads(done.stdout)["done"]
    assert report["rows_removed"] == 14 and report["files_removed"] == 14
    after = json.loads(cli("stats", "--json").stdout)
    assert after["counts"]["results"] == 14 and after["prune"]["remove"] == 0
    assert before - after["total_bytes"] >= report["bytes_freed"] > 0
    verify = cli("verify")
    assert verify.returncode == 0, describe(verify)
    bad = cli("prune", "--keep", "peaks=")
    assert bad.returncode == 2, describe(bad)
