"""Frames that cannot fit the calibration that applies are refused at ingest, nothing stored;
when none applies, they are stored and the reason is said (archive, and the installed CLI)."""

from __future__ import annotations

import datetime as dt
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from sqlalchemy import func, select

from rasterserver.archive import AcquisitionSpec, Archive, FrameSource
from rasterserver.catalog.models import Acquisition, Calibration, Frame
from rasterserver.config import Settings, sqlite_url
from rasterserver.errors import InputError
from rasterserver.frame_fit import calibration_notice, check_frame_fits
from rasterserver.optics import default_station

COMMAND = str(Path(sys.executable).with_name("rasterserver"))
#: 604 rows x 576 columns: the default camera
SHAPE = (604, 576)
#: what the issue ingested with a 604x576 calibration attached
MISFITS = {
    "300x400": (300, 400),
    "1x1": (1, 1),
    "transposed": (576, 604),
    "16000x16000": (16000, 16000),
}


def _frame(shape: tuple[int, int]) -> np.ndarray:
    # constant frames: a 16000x16000 one is 256 MB of memory, not of random numbers
    return np.full(shape, 7, np.uint8)


def _nothing_stored(archive: Archive) -> bool:
    with archive.session() as s:
        rows = s.scalar(select(func.count()).select_from(Acquisition))
        frames = s.scalar(select(func.count()).select_from(Frame))
    files = [p for p in (archive.settings.archive / "raw").rglob("*") if p.is_file()]
    return rows == 0 and frames == 0 and not files


@pytest.fixture
def archive(settings: Settings) -> Archive:
    """Patient P1, station clinic-1 calibrated for the default camera, station bare-1 without."""
    arch = Archive.create(settings)
    arch.add_patient("P1")
    arch.add_station("clinic-1")
    arch.add_station("bare-1")
    arch.add_calibration(
        "clinic-1", default_station().to_dict(), valid_from=dt.datetime(2000, 1, 1, tzinfo=dt.UTC)
    )
    yield arch
    arch.close()


@pytest.mark.parametrize("shape", list(MISFITS.values()), ids=list(MISFITS))
def test_a_frame_of_another_size_is_refused_and_nothing_stored(archive, shape) -> None:
    with pytest.raises(InputError) as refused:
        archive.ingest(
            [FrameSource(_frame(shape), name="back.npy")], patient="P1", station="clinic-1"
        )
    message = str(refused.value)
    assert message.startswith("back.npy: ")
    assert f"{shape[0]}x{shape[1]}" in message and "604x576" in message
    assert "clinic-1:1" in message
    assert _nothing_stored(archive)


def test_one_misfit_frame_refuses_the_whole_batch(archive) -> None:
    good = AcquisitionSpec([FrameSource(_frame(SHAPE), name="a")], patient="P1", station="clinic-1")
    bad = AcquisitionSpec(
        [FrameSource(_frame(SHAPE), name="b0"), FrameSource(_frame((576, 604)), name="b1")],
        patient="P1",
        station="clinic-1",
    )
    with pytest.raises(InputError, match=r"^b1: the frame is 576x604"):
        archive.ingest_many([good, bad])
    assert _nothing_stored(archive)


def test_a_fitting_frame_is_stored_with_its_calibration(archive) -> None:
    acq = archive.ingest(
        [FrameSource(_frame(SHAPE), name="back.npy")], patient="P1", station="clinic-1"
    )
    assert acq.calibration_id is not None
    assert calibration_notice(archive, acq) is None


def test_frames_are_stored_with_a_reason_when_no_calibration_applies(archive) -> None:
    odd = _frame((300, 400))
    none = archive.ingest([FrameSource(odd, name="f")], patient="P1")
    bare = archive.ingest([FrameSource(odd, name="f")], patient="P1", station="bare-1")
    body = archive.ingest(
        [FrameSource(odd, name="f", role="projector-off")],
        patient=None,
        kind="calibration",
        station="clinic-1",
    )
    assert "no station given" in calibration_notice(archive, none)
    assert "station 'bare-1' has no calibration yet" in calibration_notice(archive, bare)
    assert "calibration acquisition" in calibration_notice(archive, body)
    for acq in (none, bare, body):
        assert "not checked" in calibration_notice(archive, acq)
        # the same from the catalogue summary the HTTP API answers with
        assert calibration_notice(archive, archive.info(acq.uid)) == calibration_notice(
            archive, acq
        )


def test_a_calibration_stored_unchecked_is_named_at_ingest(archive) -> None:
    # an archive from before the checks: a broken document in the catalogue
    document = default_station().to_dict()
    document["camera"]["K"] = [[0, 0, 0]] * 3
    with archive.session() as s:
        station_id = archive.station("clinic-1", s).id
        s.add(
            Calibration(
                station_id=station_id,
                version=2,
                parameters=document,
                residuals={},
                sha256="0" * 64,
                valid_from=dt.datetime(2001, 1, 1, tzinfo=dt.UTC),
            )
        )
    with pytest.raises(
        InputError,
        match=r"calibration clinic-1:2: camera\.K: focal lengths.*"
        r"store a corrected calibration",
    ):
        archive.ingest([FrameSource(_frame(SHAPE), name="f")], patient="P1", station="clinic-1")
    assert _nothing_stored(archive)


def test_check_frame_fits_names_both_sizes() -> None:
    station = default_station()
    check_frame_fits(SHAPE, station)
    check_frame_fits((3, 3), object())  # not a station: nothing to check
    with pytest.raises(InputError, match=r"576x604 .* is 604x576"):
        check_frame_fits((576, 604), station)


# --- the installed command ------------------------------------------------------------------


@pytest.fixture
def cli_archive(tmp_path: Path) -> Settings:
    root = tmp_path / "archive"
    settings = Settings(archive=root, database_url=sqlite_url(root))
    with Archive.create(settings) as arch:
        arch.add_patient("P1")
        arch.add_station("clinic-1")
        arch.add_station("bare-1")
        arch.add_calibration(
            "clinic-1",
            default_station().to_dict(),
            valid_from=dt.datetime(2000, 1, 1, tzinfo=dt.UTC),
        )
    return settings


def _ingest(settings: Settings, path: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [
            COMMAND,
            "--archive",
            str(settings.archive),
            "--database-url",
            settings.database_url,
            "ingest",
            str(path),
            *args,
        ],
        capture_output=True,
        text=True,
        check=False,
        timeout=120,
    )


def test_installed_ingest_refuses_misfit_frames_and_warns_without_calibration(
    cli_archive, tmp_path
) -> None:
    misfit, fitting = tmp_path / "transposed.npy", tmp_path / "back.npy"
    np.save(misfit, _frame((576, 604)))
    np.save(fitting, _frame(SHAPE))
    refused = _ingest(cli_archive, misfit, "--patient", "P1", "--station", "clinic-1")
    assert refused.returncode == 2 and "Traceback" not in refused.stderr
    assert refused.stderr.startswith("error: transposed.npy: the frame is 576x604")
    assert "604x576" in refused.stderr and refused.stdout == ""
    with Archive(cli_archive) as archive:
        assert _nothing_stored(archive)
    stored = _ingest(cli_archive, fitting, "--patient", "P1", "--station", "clinic-1")
    assert stored.returncode == 0 and stored.stderr == "", stored.stderr
    warned = _ingest(cli_archive, misfit, "--patient", "P1", "--station", "bare-1")
    assert warned.returncode == 0 and "frame(s) stored" in warned.stdout
    assert warned.stderr.startswith("warning: station 'bare-1' has no calibration yet")
