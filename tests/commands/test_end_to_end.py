"""The installed ``rasterserver`` on a processed archive, each command in a fresh process, as
an archive administrator runs them; and every exit code of the README's table produced by a
command that should produce it (issue 11).

A fresh process matters: it has imported nothing but what the command imports (the demo's
in-process verify passed while ``rasterserver verify`` reported every stored result corrupt).
The archive is built once for the module with the CLI (simulate --ingest, process) on the
embedded default (SQLite inside the archive folder).
"""

from __future__ import annotations

import json
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from installed_cli import (
    TRACEBACK,
    describe,
    installed_command,
    run_installed,
    sigint_as_from_a_terminal,
)

sys.path.insert(0, str(Path(__file__).parents[1] / "calibration"))
from calibration_frames import rendered_dir

#: A uid no acquisition has.
UNKNOWN = "0123456789abcdef0123456789abcdef"


class Processed:
    """The module's archive: one simulated acquisition of patient P1, processed."""

    def __init__(self, root: Path, uid: str) -> None:
        self.root = root
        self.archive = root / "archive"
        self.simulated = root / "simulated"
        self.uid = uid

    def run(self, *args: str, code: int = 0, archive: Path | None = None) -> str:
        """Run a command on the archive; assert its exit code and that no traceback shows.

        Returns
        -------
        str
            Its standard output.
        """
        done = run_installed(*args, archive=archive or self.archive)
        assert TRACEBACK not in done.stdout + done.stderr, describe(done)
        assert done.returncode == code, describe(done)
        return done.stdout


@pytest.fixture(scope="module")
def processed(tmp_path_factory: pytest.TempPathFactory) -> Processed:
    root = tmp_path_factory.mktemp("end-to-end")
    archive = root / "archive"
    out = Processed(root, "").run(
        "simulate", "back", "--supersample", "1", "--ingest", "--patient", "P1",
        "-o", str(root / "simulated"), archive=archive,
    )  # fmt: skip
    (uid,) = [line.split()[1] for line in out.splitlines() if line.startswith("ingested ")]
    state = Processed(root, uid)
    done = state.run("process", "--all-unprocessed")
    assert f"{uid}\tdone\t" in done
    return state


def test_verify_finds_no_problem(processed: Processed) -> None:
    """Defect 1: stored peaks / lines / order / numbers results were reported corrupt
    ("record kind ... is unknown here") by a verify in a fresh process, exit 5."""
    out = processed.run("verify")
    assert "unknown here" not in out and "corrupt" not in out
    assert out.strip().splitlines()[-1].endswith("OK"), out


def test_verify_repair_dry_run_has_nothing_to_do(processed: Processed) -> None:
    out = processed.run("verify", "--repair", "--dry-run")
    assert "corrupt" not in out and "would quarantine" not in out and "would delete" not in out


def test_list_and_list_json(processed: Processed) -> None:
    assert processed.run("list").split("\t")[:3] == [processed.uid, "P1", "patient"]
    (line,) = processed.run("list", "--json").splitlines()
    record = json.loads(line)
    assert record["uid"] == processed.uid and record["patient"] == "P1"
    assert record["frames"] == [
        {"index": 0, "role": "raster", "shape": [604, 576], "dtype": "uint8"}
    ]


@pytest.mark.parametrize("fmt", ["ply", "obj", "stl", "csv"])
def test_export_each_format(processed: Processed, fmt: str) -> None:
    target = processed.root / "exports" / f"back.{fmt}"
    target.parent.mkdir(exist_ok=True)
    out = processed.run("export", processed.uid, "-f", fmt, "-o", str(target))
    assert f"written to {target}" in out
    data = target.read_bytes()
    if fmt == "ply":
        assert data.startswith(b"ply\n") and b"element face" in data
    elif fmt == "obj":
        assert b"\nv " in data and b"\nf " in data
    elif fmt == "stl":  # binary: 80-byte header, count, 50 bytes a triangle
        count = int.from_bytes(data[80:84], "little")
        assert count > 1000 and len(data) == 84 + 50 * count
    else:
        lines = data.decode().splitlines()
        assert lines[0] == "x_mm,y_mm,z_mm,line_number,column,row,peak_area"
        assert len(lines) > 1000
    assert [p.name for p in target.parent.iterdir() if ".tmp-" in p.name] == []


def test_export_in_the_patient_frame_with_its_sidecar(processed: Processed) -> None:
    # the body-fixed frame of the analysis: origin DM, X right, Y up (DM -> VP), Z posterior
    import numpy as np
    import open3d as o3d

    folder = processed.root / "exports"
    folder.mkdir(exist_ok=True)
    station, patient = folder / "station.ply", folder / "patient.ply"
    processed.run("export", processed.uid, "-f", "ply", "-o", str(station))
    out = processed.run(
        "export", processed.uid, "-f", "ply", "-o", str(patient), "--frame", "patient"
    )
    assert "(patient frame, mm)" in out
    sidecar = json.loads((folder / "patient.ply.json").read_text())
    assert sidecar["acquisition"] == processed.uid and sidecar["units"] == "mm"
    assert sidecar["frame"]["name"] == "patient" and sidecar["result"]["stage"] == "mesh"
    assert json.loads((folder / "station.ply.json").read_text())["frame"]["name"] == "station"
    origin = np.array(sidecar["frame"]["origin_world_mm"])
    axes = np.array(sidecar["frame"]["axes_in_world"])
    np.testing.assert_allclose(axes @ axes.T, np.eye(3), atol=1e-9)
    assert np.linalg.det(axes) > 0.999  # right-handed
    world = np.asarray(o3d.io.read_triangle_mesh(str(station)).vertices)
    body = np.asarray(o3d.io.read_triangle_mesh(str(patient)).vertices)
    np.testing.assert_allclose(body, (world - origin) @ axes.T, atol=1e-6)
    # Y up: the top of the back (small world y) has large patient-frame y
    assert axes[1] @ np.array([0.0, -1.0, 0.0]) > 0.95
    assert axes[2] @ np.array([0.0, 0.0, -1.0]) > 0.9  # Z posterior: towards the camera


def test_processing_a_processed_acquisition_reuses_everything(processed: Processed) -> None:
    out = processed.run("process", processed.uid)
    assert out.startswith(f"{processed.uid}\tdone\t0 computed, ")
    assert " reused" in out


def test_runs_list(processed: Processed) -> None:
    out = processed.run("runs", "list", processed.uid)
    assert "done" in out and "failed" not in out and "running" not in out
    assert len(out.strip().splitlines()) >= 2  # the first processing and the reuse


# --- every exit code of the README's table --------------------------------------------------


def test_exit_2_3_4_bad_input_not_found_conflict(processed: Processed) -> None:
    target = str(processed.root / "mesh.csv")
    processed.run("export", processed.uid, "-f", "csv", "--what", "mesh", "-o", target, code=2)
    processed.run("process", UNKNOWN, code=3)  # defect 6: was 1
    processed.run("patient", "add", "P1", code=4)


def test_exit_1_5_on_a_damaged_copy(processed: Processed) -> None:
    """1: acquisitions of one ``process`` failed for different reasons; 5: ``verify`` finds
    a stored result missing (and ``--repair --dry-run`` leaves it for a person)."""
    copy = processed.root / "damaged"
    shutil.copytree(processed.archive, copy)
    processed.run("station", "add", "other", archive=copy)
    calibration = str(processed.simulated / "calibration.json")
    processed.run("station", "add-calibration", "other", calibration, archive=copy)
    # an unknown uid (3) and a calibration of another station (2): exit 1, both listed
    out = processed.run(
        "process", UNKNOWN, processed.uid, "--calibration", "other:1", code=1, archive=copy
    )
    assert out.count("\tfailed\t") == 2
    victim = next(p for p in sorted((copy / "derived").rglob("*")) if p.is_file())
    victim.unlink()  # a stored result lost (a disk error, a careless cleanup)
    out = processed.run("verify", code=5, archive=copy)
    assert "missing" in out
    processed.run("verify", "--repair", "--dry-run", code=5, archive=copy)


def test_exit_6_catalogue_schema_not_current(processed: Processed) -> None:
    old = processed.root / "old-schema"
    processed.run("db", "upgrade", "0008", archive=old)
    done = run_installed("list", archive=old)
    assert done.returncode == 6 and "rasterserver db upgrade" in done.stderr, describe(done)


def test_exit_7_calibration_worse_than_the_bounds() -> None:
    done = run_installed("calibrate", str(rendered_dir()), "--dry-run", "--max-rms-px", "0.001")
    assert TRACEBACK not in done.stdout + done.stderr, describe(done)
    assert done.returncode == 7 and "calibration rejected" in done.stderr, describe(done)


def test_exit_8_catalogue_unreachable(processed: Processed) -> None:
    done = run_installed(
        "--database-url", "postgresql+psycopg://u@127.0.0.1:1/x", "list", archive=processed.archive
    )
    assert done.returncode == 8 and done.stderr.startswith("error: cannot use the catalogue")
    assert TRACEBACK not in done.stderr, describe(done)


def test_exit_130_interrupted(processed: Processed) -> None:
    """Ctrl-C in the middle of the work: exit 130 (the shell's code for SIGINT), no
    traceback."""
    out = processed.root / "interrupted"
    with subprocess.Popen(
        [installed_command(), "simulate", "back", "--visits", "5", "-o", str(out)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=sigint_as_from_a_terminal,
    ) as proc:
        assert proc.stderr is not None
        first = proc.stderr.readline()  # "[1/5] rendering back ...": the work has begun
        assert "rendering" in first, first
        time.sleep(0.5)
        proc.send_signal(signal.SIGINT)
        assert proc.stdout is not None
        # read the pipes themselves: communicate() would skip what readline() buffered
        stderr, stdout = proc.stderr.read(), proc.stdout.read()
        proc.wait(timeout=120)
    assert proc.returncode == 130, (proc.returncode, stdout, stderr)
    assert TRACEBACK not in stdout + stderr
