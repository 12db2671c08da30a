"""Malformed input on the command line: a sentence and the documented exit code, never a
traceback, and nothing stored or half written (issue 11, defects 5 and 6).

Every case runs the installed ``rasterserver`` in a fresh process. The exit codes are the
README's table: 2 bad input, 3 not found, 4 conflict, 8 the archive cannot be used. Exit 1
with a traceback is a failure of the case, as is any other code than the one documented.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pytest
from installed_cli import TRACEBACK, describe, run_installed

from rasterserver.archive import Archive
from rasterserver.cli import main
from rasterserver.config import Settings
from rasterserver.optics import default_station

sys.path.insert(0, str(Path(__file__).parents[1] / "calibration"))
from calibration_frames import rendered_dir


class Case(NamedTuple):
    """One malformed input: the arguments (``{name}`` fields filled from the workspace),
    the exit code the README documents for it, and words its message must hold."""

    id: str
    args: tuple[str, ...]
    code: int
    words: str = ""
    needs: str = ""  # a workspace entry that may be missing here ("read_only")


def _case(case_id: str, args: str, code: int, words: str = "", needs: str = "") -> Case:
    return Case(case_id, tuple(args.split()), code, words, needs)


CASES = [
    # --- defect 5: tracebacks instead of errors --------------------------------------------
    _case(
        "control-point-nan",
        "calibrate {frames} --dry-run --control-points {cp_nan}",
        2,
        "not a finite number",
    ),
    _case(
        "control-point-inf",
        "calibrate {frames} --dry-run --control-points {cp_inf}",
        2,
        "not a finite number",
    ),
    _case(
        "control-points-deep",
        "calibrate {frames} --dry-run --control-points {deep}",
        2,
        "nested too deeply",
    ),
    _case(
        "control-points-folder",
        "calibrate {frames} --dry-run --control-points {folder}",
        2,
        "folder",
    ),
    _case("calibrate-reference-nan", "calibrate {frames} --dry-run --reference {cal_nan}", 2),
    _case(
        "export-missing-folder", "export {uid} -f ply -o {root}/missing/m.ply", 2, "does not exist"
    ),
    _case(
        "export-read-only-folder",
        "export {uid} -f ply -o {read_only}/m.ply",
        2,
        "cannot write",
        "read_only",
    ),
    _case("export-to-a-folder", "export {uid} -f ply -o {folder}", 2, "is a folder"),
    _case("export-to-a-device", "export {uid} -f csv -o /dev/null", 2, "not a regular file"),
    _case("export-under-a-file", "export {uid} -f ply -o {exists}/m.ply", 2),
    _case(
        "reconstruct-missing-folder",
        "reconstruct {frame} --calibration {cal} -o {root}/missing/c.ply",
        2,
        "does not exist",
    ),
    _case(
        "reconstruct-read-only-folder",
        "reconstruct {frame} --calibration {cal} -o {read_only}/c.ply",
        2,
        "cannot write",
        "read_only",
    ),
    _case(
        "reconstruct-to-a-folder",
        "reconstruct {frame} --calibration {cal} -o {folder_ply}",
        2,
        "is a folder",
    ),
    _case(
        "reconstruct-overlay-not-an-image",
        "reconstruct {frame} --calibration {cal} -o {root}/c.ply --overlay {root}/o.txt",
        2,
        "--overlay",
    ),
    _case(
        "calibrate-out-missing-folder",
        "calibrate {frames} --dry-run -o {root}/missing/cal.json",
        2,
        "does not exist",
    ),
    _case(
        "calibrate-out-read-only-folder",
        "calibrate {frames} --dry-run -o {read_only}/cal.json",
        2,
        "cannot write",
        "read_only",
    ),
    _case("calibrate-out-a-folder", "calibrate {frames} --dry-run -o {folder}", 2, "is a folder"),
    _case(
        "calibrate-report-not-an-image",
        "calibrate {frames} --dry-run --report {root}/r.txt",
        2,
        "name an image",
    ),
    _case(
        "export-calibration-missing-folder",
        "export-calibration S1 -o {root}/missing/cal.json",
        2,
        "does not exist",
    ),
    _case(
        "audit-export-missing-folder",
        "audit export -o {root}/missing/audit.json",
        2,
        "does not exist",
    ),
    _case("simulate-negative-seed", "simulate back --seed -1 -o {root}/sim", 2, "--seed"),
    _case(
        "simulate-negative-random-back",
        "simulate back --random-back -5 -o {root}/sim",
        2,
        "--random-back",
    ),
    _case(
        "simulate-body-negative-seed",
        "simulate calibration-body --seed -1 -o {root}/sim",
        2,
        "--seed",
    ),
    _case("simulate-out-is-a-file", "simulate back -o {exists}", 2, "not a folder"),
    _case(
        "simulate-body-out-is-a-file", "simulate calibration-body -o {exists}", 2, "not a folder"
    ),
    _case("simulate-out-under-a-file", "simulate back -o {exists}/sim", 2, "not a folder"),
    _case(
        "simulate-out-read-only", "simulate back -o {read_only}/sim", 2, "cannot write", "read_only"
    ),
    # --- defect 5: calibration and raster documents (validated in rasterserver.documents) --
    _case("add-calibration-array", "station add-calibration S1 {cal_array}", 2),
    _case("add-calibration-deep", "station add-calibration S1 {deep}", 2),
    _case("add-calibration-nan", "station add-calibration S1 {cal_nan}", 2),
    _case("add-calibration-inf", "station add-calibration S1 {cal_inf}", 2),
    _case("add-calibration-folder", "station add-calibration S1 {folder}", 2),
    _case("add-calibration-empty", "station add-calibration S1 {empty}", 2),
    _case("add-raster-array", "station add-raster S1 {raster_array}", 2),
    _case("add-raster-deep", "station add-raster S1 {deep}", 2),
    _case("add-raster-folder", "station add-raster S1 {folder}", 2),
    _case(
        "reconstruct-calibration-array",
        "reconstruct {frame} --calibration {cal_array} -o {root}/c.ply",
        2,
    ),
    _case(
        "reconstruct-calibration-deep",
        "reconstruct {frame} --calibration {deep} -o {root}/c.ply",
        2,
    ),
    _case(
        "reconstruct-calibration-nan",
        "reconstruct {frame} --calibration {cal_nan} -o {root}/c.ply",
        2,
    ),
    _case(
        "reconstruct-calibration-folder",
        "reconstruct {frame} --calibration {folder} -o {root}/c.ply",
        2,
    ),
    _case(
        "reconstruct-raster-array",
        "reconstruct {frame} --calibration {cal} --raster {raster_array} -o {root}/c.ply",
        2,
    ),
    # --- defect 6: exit codes ----------------------------------------------------------------
    _case(
        "process-unknown-uid", "process 0123456789abcdef0123456789abcdef", 3, "unknown acquisition"
    ),
    _case(
        "process-unknown-plugin",
        "process {uid} --stage peaks=no-such-plugin",
        3,
        "no stage plugin named",
    ),
    _case("process-unknown-stage", "process {uid} --until no-such-stage", 2),
    _case("process-unknown-calibration", "process {uid} --calibration no-such-station:1", 3),
    _case("process-calibration-not-a-version", "process {uid} --calibration S1:x", 2),
    _case(
        "export-unknown-uid", "export 0123456789abcdef0123456789abcdef -f ply -o {root}/m.ply", 3
    ),
    _case("export-mesh-as-csv", "export {uid} -f csv --what mesh -o {root}/m.csv", 2),
    _case("export-not-processed", "export {uid} -f ply -o {root}/m.ply", 3),
    _case("runs-unknown-uid", "runs list 0123456789abcdef0123456789abcdef", 3),
    _case("export-calibration-unknown-station", "export-calibration nowhere -o {root}/cal.json", 3),
    _case("export-calibration-bad-version", "export-calibration S1:x -o {root}/cal.json", 2),
    # --- found by trying: dates, raw frames, files, names, numbers ----------------------------
    _case("list-bad-date", "list --since 2025-13-45", 2),
    _case("list-unknown-kind", "list --kind no-such-kind", 2, "--kind"),
    _case("list-unknown-patient", "list --patient nobody", 3),
    _case("list-zero-limit", "list --limit 0", 2),
    _case(
        "ingest-time-without-zone", "ingest {frame} --patient P1 --acquired-at 2025-03-01T10:15", 2
    ),
    _case("ingest-bad-visit-date", "ingest {frame} --patient P1 --visit-date 2025-02-30", 2),
    _case("ingest-empty-file", "ingest {empty} --patient P1", 2, "empty"),
    _case("ingest-folder", "ingest {folder} --patient P1", 2),
    _case("ingest-text-as-image", "ingest {exists} --patient P1", 2),
    _case(
        "ingest-raw-float-dtype",
        "ingest {raw} --patient P1 --shape 4x4 --dtype float64",
        2,
        "float64",
    ),
    _case("ingest-raw-bad-shape", "ingest {raw} --patient P1 --shape abc --dtype uint8", 2),
    _case("ingest-raw-negative-shape", "ingest {raw} --patient P1 --shape -4x4 --dtype uint8", 2),
    _case("ingest-raw-size-mismatch", "ingest {raw} --patient P1 --shape 5x5 --dtype uint8", 2),
    _case(
        "ingest-raw-huge-shape",
        "ingest {raw} --patient P1 --shape 99999999999x99999999999 --dtype uint16",
        2,
    ),
    _case("ingest-unknown-patient", "ingest {frame} --patient nobody", 3),
    _case("ingest-unknown-station", "ingest {frame} --patient P1 --station nowhere", 3),
    _case("ingest-unknown-role", "ingest {frame} --patient P1 --role bogus", 2),
    _case("ingest-unknown-kind", "ingest {frame} --patient P1 --kind bogus", 2),
    _case("patient-bad-birth-date", "patient add P2 --birth-date 2025-02-30", 2),
    _case("patient-unknown-sex", "patient add P2 --sex alien", 2),
    _case("patient-empty-identifier", "patient add ''", 2),
    _case("patient-duplicate", "patient add P1", 4),
    _case("station-duplicate", "station add S1", 4),
    _case("verify-negative-min-age", "verify --min-age -1", 2),
    _case("token-for-unknown-account", "token create nobody", 3),
    _case("token-id-not-a-number", "token revoke abc", 2),
    _case("db-unknown-revision", "db upgrade no-such-revision", 2, "no-such-revision"),
    _case("serve-port-out-of-range", "serve --port 99999", 2, "--port"),
    _case("serve-no-workers", "serve --workers 0", 2, "--workers"),
]

#: Cases with global options before the command (not the workspace's archive).
ARCHIVE_CASES = [
    _case(
        "database-url-not-a-url",
        "--archive {archive} --database-url not-a-url list",
        2,
        "catalogue URL",
    ),
    _case(
        "database-unreachable",
        "--archive {archive} --database-url postgresql+psycopg://u:secret@127.0.0.1:1/x list",
        8,
        "cannot use the catalogue",
    ),
    _case("archive-is-a-file", "--archive {exists} list", 8, "cannot use"),
]


def _read_only_folder(root: Path) -> Path | None:
    """A folder nothing can be created in: a read-only one, or sysfs when root ignores that."""
    folder = root / "read-only"
    folder.mkdir()
    folder.chmod(0o555)
    try:
        (folder / "probe").touch()
    except PermissionError:
        return folder
    (folder / "probe").unlink()
    try:
        Path("/sys/rasterserver-probe").touch()
    except OSError:
        return Path("/sys")
    return None


@pytest.fixture(scope="module")
def workspace(tmp_path_factory: pytest.TempPathFactory) -> dict[str, str]:
    """Files for the cases and an archive with patient P1, station S1 (no calibration) and
    one acquisition, ``uid``, that is not processed."""
    root = tmp_path_factory.mktemp("malformed")
    archive = root / "archive"
    station = default_station()
    frame = root / "frame.npy"
    np.save(frame, np.random.default_rng(11).integers(0, 256, (604, 576), dtype=np.uint8))
    document = station.to_dict()
    paths: dict[str, Path] = {
        "root": root,
        "frame": frame,
        "cal": station.save(root / "cal.json"),
        "folder": root / "a-folder",
        "folder_ply": root / "cloud.ply",
        "exists": root / "exists.txt",
        "empty": root / "empty.json",
        "deep": root / "deep.json",
        "raw": root / "frame.raw",
        "cal_array": root / "cal-array.json",
        "cal_nan": root / "cal-nan.json",
        "cal_inf": root / "cal-inf.json",
        "raster_array": root / "raster-array.json",
        "cp_nan": root / "cp-nan.json",
        "cp_inf": root / "cp-inf.json",
    }
    paths["folder"].mkdir()
    paths["folder_ply"].mkdir()
    paths["exists"].write_text("not an image, not a folder\n")
    paths["empty"].write_bytes(b"")
    paths["deep"].write_text("[" * 100_000 + "]" * 100_000)
    paths["raw"].write_bytes(bytes(16))
    paths["cal_array"].write_text(json.dumps([document]))
    for name, value in (("cal_nan", float("nan")), ("cal_inf", float("inf"))):
        broken = json.loads(json.dumps(document))
        broken["camera"]["K"][0][0] = value
        paths[name].write_text(json.dumps(broken))  # NaN / Infinity, as Python writes them
    paths["raster_array"].write_text(json.dumps([station.raster_definition.to_dict()]))
    frames = rendered_dir()
    points = json.loads((frames / "control_points.json").read_text())
    for name, value in (("cp_nan", float("nan")), ("cp_inf", float("inf"))):
        broken = json.loads(json.dumps(points))
        broken["points"][3]["x"] = value
        paths[name].write_text(json.dumps(broken))
    read_only = _read_only_folder(root)

    settings = Settings(archive=archive, database_url=f"sqlite:///{archive / 'catalog.sqlite'}")
    base = ["--archive", str(archive), "--database-url", settings.database_url]
    for args in (
        ["db", "upgrade"],
        ["patient", "add", "P1"],
        ["station", "add", "S1"],
        ["ingest", str(frame), "--patient", "P1"],
    ):
        assert main([*base, *args]) == 0, args
    with Archive(settings) as opened:
        (acquisition,) = opened.find(limit=10)
    values = {name: str(path) for name, path in paths.items()}
    values.update(
        archive=str(archive),
        database_url=settings.database_url,
        frames=str(frames),
        uid=acquisition.uid,
    )
    if read_only is not None:
        values["read_only"] = str(read_only)
    return values


def _run(
    case: Case, workspace: dict[str, str], *, archive: bool
) -> subprocess.CompletedProcess[str]:
    if case.needs and case.needs not in workspace:
        pytest.skip(f"no {case.needs.replace('_', ' ')} folder can be made for this user")
    args = [arg.format(**workspace) for arg in case.args]
    args = ["" if arg == "''" else arg for arg in args]
    root = Path(workspace["root"])
    before = {p for p in root.rglob("*") if "catalog.sqlite" not in p.name}
    done = run_installed(
        *args,
        archive=Path(workspace["archive"]) if archive else None,
        database_url=workspace["database_url"] if archive else None,
        timeout=120,  # every case is refused before the work: a case still running failed
    )
    output = done.stdout + done.stderr
    assert TRACEBACK not in output, describe(done)
    assert done.returncode == case.code, describe(done)
    assert case.words in output, describe(done)
    # nothing half written: no temporary file, no new file or folder beside the inputs
    after = {p for p in root.rglob("*") if "catalog.sqlite" not in p.name}
    assert sorted(map(str, after - before)) == [], describe(done)
    return done


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_malformed_input_is_refused_with_its_exit_code(
    case: Case, workspace: dict[str, str]
) -> None:
    _run(case, workspace, archive=True)


@pytest.mark.parametrize("case", ARCHIVE_CASES, ids=[c.id for c in ARCHIVE_CASES])
def test_an_unusable_archive_or_catalogue_is_refused(case: Case, workspace: dict[str, str]) -> None:
    done = _run(case, workspace, archive=False)
    assert "secret" not in done.stderr + done.stdout  # the URL's password is never shown


def test_nothing_was_stored_by_the_refused_commands(workspace: dict[str, str]) -> None:
    """After every case (module order): still one patient, one station without calibration,
    and the one acquisition."""
    settings = Settings(archive=Path(workspace["archive"]), database_url=workspace["database_url"])
    with Archive(settings) as archive:
        assert [p.identifier for p in archive.patients()] == ["P1"]
        assert [s.name for s in archive.stations()] == ["S1"]
        assert archive.calibrations("S1") == []
        assert [a.uid for a in archive.find(limit=10)] == [workspace["uid"]]
    raw = Path(workspace["archive"]) / "raw"
    assert len([p for p in raw.rglob("*") if p.is_file()]) == 1
    shutil.rmtree(Path(workspace["root"]) / "read-only", ignore_errors=True)
