"""``rasterserver station add-calibration`` and ``add-raster``: a refused document is one line on
stderr and exit 2, never a traceback, and nothing is stored.

The installed command runs in a subprocess for the cases of the issue; the whole table of
broken documents (tests/test_documents.py) runs in-process.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from sqlalchemy import func, select
from test_documents import BROKEN_CALIBRATIONS, BROKEN_RASTERS, good_calibration, good_raster

from rasterserver.archive import Archive
from rasterserver.catalog.models import Calibration, Raster
from rasterserver.cli import main
from rasterserver.config import Settings, sqlite_url

COMMAND = str(Path(sys.executable).with_name("rasterserver"))


def _stored(settings: Settings) -> tuple[int, int]:
    """How many calibrations and rasters the archive holds."""
    with Archive(settings) as archive, archive.session() as s:
        return (
            s.scalar(select(func.count()).select_from(Calibration)) or 0,
            s.scalar(select(func.count()).select_from(Raster)) or 0,
        )


def _file(tmp_path: Path, name: str, document: Any) -> Path:
    path = tmp_path / name
    # allow_nan: the documents with NaN are written as Python's json writes them
    path.write_text(json.dumps(document, allow_nan=True), encoding="utf-8")
    return path


def _case(name: str, table: list[tuple[str, Any, str, str]]) -> tuple[Any, str]:
    found = next(c for c in table if c[0] == name)
    return found[1], found[3]


def _archive(root: Path) -> Settings:
    settings = Settings(archive=root, database_url=sqlite_url(root))
    with Archive.create(settings) as archive:
        archive.add_station("clinic-1")
    return settings


@pytest.fixture
def archive_dir(tmp_path: Path) -> Settings:
    """An SQLite archive with station clinic-1 (the command's behaviour does not depend on the
    catalogue; the archive tests cover both)."""
    return _archive(tmp_path / "archive")


@pytest.fixture(scope="module")
def shared(tmp_path_factory: pytest.TempPathFactory) -> Settings:
    """One archive for the whole table of refused documents: each leaves it empty."""
    return _archive(tmp_path_factory.mktemp("shared") / "archive")


def _main(settings: Settings, *args: str) -> int:
    return main(
        ["--archive", str(settings.archive), "--database-url", settings.database_url, *args]
    )


def _run(settings: Settings, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [
            COMMAND,
            "--archive",
            str(settings.archive),
            "--database-url",
            settings.database_url,
            *args,
        ],
        capture_output=True,
        text=True,
        check=False,
        timeout=120,
    )


# the broken files of the issue, and the unreadable ones of defect 5
_ISSUE_CALIBRATIONS = [
    "K-all-zeros",
    "K-missing",
    "projector-missing",
    "foreign-format",
    "R-not-orthonormal",
    "negative-width",
    "zero-baseline",
    "singular-K",
    "an-array",
    "a-raster-definition",
]


def _unreadable(tmp_path: Path, kind: str) -> Path:
    path = tmp_path / f"{kind}.json"
    if kind == "directory":
        path.mkdir()
    elif kind == "binary":
        path.write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR")
    elif kind == "deeply-nested":
        path.write_text("[" * 100_000 + "]" * 100_000)
    elif kind == "infinity":
        path.write_text(json.dumps(good_calibration()).replace("2000.0", "Infinity", 1))
    return path


@pytest.mark.parametrize(
    "case", [*_ISSUE_CALIBRATIONS, "directory", "binary", "deeply-nested", "infinity"]
)
def test_installed_command_refuses_broken_calibrations(archive_dir, tmp_path, case) -> None:
    if case in _ISSUE_CALIBRATIONS:
        document, words = _case(case, BROKEN_CALIBRATIONS)
        path = _file(tmp_path, f"{case}.json", document)
    else:
        path, words = _unreadable(tmp_path, case), ""
    done = _run(archive_dir, "station", "add-calibration", "clinic-1", str(path))
    assert done.returncode == 2, done.stderr
    assert "Traceback" not in done.stderr and done.stdout == ""
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {path.name}: ") and words in lines[0]
    assert _stored(archive_dir) == (0, 0)


@pytest.mark.parametrize("case", ["a-1", "a-calibration", "directory"])
def test_installed_command_refuses_broken_rasters(archive_dir, tmp_path, case) -> None:
    if case in ("directory", "binary"):
        path, words = _unreadable(tmp_path, case), ""
    else:
        document, words = _case(case, BROKEN_RASTERS)
        path = _file(tmp_path, f"{case}.json", document)
    done = _run(archive_dir, "station", "add-raster", "r1", str(path))
    assert done.returncode == 2, done.stderr
    assert "Traceback" not in done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {path.name}: ") and words in lines[0]
    assert _stored(archive_dir) == (0, 0)


def test_installed_command_stores_good_documents(archive_dir, tmp_path) -> None:
    raster = _run(
        archive_dir,
        "station",
        "add-raster",
        "default",
        str(_file(tmp_path, "raster.json", good_raster())),
    )
    assert raster.returncode == 0, raster.stderr
    calibration = _run(
        archive_dir,
        "station",
        "add-calibration",
        "clinic-1",
        str(_file(tmp_path, "cal.json", good_calibration())),
        "--raster",
        "default",
    )
    assert calibration.returncode == 0, calibration.stderr
    assert "calibration version 1 stored" in calibration.stdout
    assert _stored(archive_dir) == (1, 1)


@pytest.mark.parametrize(
    ("document", "field", "words"),
    [c[1:] for c in BROKEN_CALIBRATIONS],
    ids=[c[0] for c in BROKEN_CALIBRATIONS],
)
def test_every_broken_calibration_exits_2(shared, tmp_path, capsys, document, field, words) -> None:
    path = _file(tmp_path, "cal.json", document)
    assert _main(shared, "station", "add-calibration", "clinic-1", str(path)) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: cal.json: ") and field in err and words in err
    assert _stored(shared) == (0, 0)


@pytest.mark.parametrize(
    ("document", "field", "words"),
    [c[1:] for c in BROKEN_RASTERS],
    ids=[c[0] for c in BROKEN_RASTERS],
)
def test_every_broken_raster_exits_2(shared, tmp_path, capsys, document, field, words) -> None:
    path = _file(tmp_path, "raster.json", document)
    assert _main(shared, "station", "add-raster", "r1", str(path)) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: raster.json: ") and field in err and words in err
    assert _stored(shared) == (0, 0)


def _frames_dir(tmp_path: Path) -> Path:
    """A folder calibrate reads up to its documents: two blank frames and the control points."""
    from rasterserver.simulator.calibration_body import control_points, write_control_points

    folder = tmp_path / "frames"
    folder.mkdir()
    for state in ("off", "on"):
        np.save(folder / f"config0-projector-{state}.npy", np.zeros((20, 20), np.uint8))
    write_control_points(folder / "control_points.json", control_points(0))
    return folder


@pytest.mark.parametrize("option", ["--raster", "--reference"])
@pytest.mark.parametrize("case", ["directory", "infinity", "deeply-nested", "binary"])
def test_calibrate_reads_its_documents_through_the_same_checks(
    tmp_path, capsys, option, case
) -> None:
    path = _unreadable(tmp_path, case)
    code = main(["calibrate", str(_frames_dir(tmp_path)), "--dry-run", option, str(path)])
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.startswith(f"error: {path.name}: ") and "Traceback" not in err


@pytest.mark.parametrize("option", ["--calibration", "--raster"])
def test_reconstruct_refuses_a_directory_and_a_swapped_document(tmp_path, capsys, option) -> None:
    frame = tmp_path / "frame.npy"
    np.save(frame, np.zeros((604, 576), np.uint8))
    calibration = _file(tmp_path, "cal.json", good_calibration())
    raster = _file(tmp_path, "raster.json", good_raster())
    folder = _unreadable(tmp_path, "directory")
    for given, words in (
        (folder, "is a directory"),
        (raster if option == "--calibration" else calibration, "this is a"),
    ):
        args = {"--calibration": str(calibration), "--raster": str(raster), option: str(given)}
        code = main(
            [
                "reconstruct",
                str(frame),
                *[x for kv in args.items() for x in kv],
                "-o",
                str(tmp_path / "out.ply"),
            ]
        )
        err = capsys.readouterr().err
        assert code == 2 and err.startswith(f"error: {given.name}: ") and words in err, err
