"""Commands load only what they use: ``--help``, ``list`` and ``verify`` start without the
heavy packages (issue 17).

Two views, both through fresh processes of the installed interpreter and command:

* a small hook imports :mod:`rasterserver.cli`, runs the command in-process with
  :func:`rasterserver.cli.main`, and reports ``sys.modules`` afterwards (whatever imported
  a module, and however);
* the installed ``rasterserver`` console script itself, run with ``PYTHONPROFILEIMPORTTIME``
  (the environment's ``-X importtime``), whose import log on stderr names every module loaded.

The archive they run on holds one simulated acquisition processed through every stage, so
that ``verify`` reads stored results of every built-in record kind.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from installed_cli import describe, installed_command, run_installed

from rasterserver.archive import Archive
from rasterserver.config import Settings, sqlite_url

#: Packages that ``--help``, ``list`` and ``verify`` must not load: the 3-D and numerical
#: stack of the stages (with numba's compiler), distributed computing, plotting, the HTTP
#: server and the simulator.
FORBIDDEN = (
    "open3d",
    "scipy",
    "numba",
    "llvmlite",
    "dask",
    "distributed",
    "matplotlib",
    "fastapi",
    "uvicorn",
    "rasterserver.simulator",
)

#: Runs the CLI in-process and writes the loaded modules (and the exit code) as JSON to the
#: file named by the first argument; the rest are the command's arguments.
HOOK = """
import json, sys
from rasterserver.cli import main
report, args = sys.argv[1], sys.argv[2:]
code = main(args)
with open(report, "w") as f:
    json.dump({"exit": code, "modules": sorted(sys.modules)}, f)
"""


def forbidden(modules: list[str] | set[str]) -> list[str]:
    """The modules of ``modules`` that belong to a :data:`FORBIDDEN` package."""
    return sorted(m for m in modules if any(m == f or m.startswith(f + ".") for f in FORBIDDEN))


def clean_env() -> dict[str, str]:
    """The test's environment without RASTERSERVER_* settings and import-time logging."""
    drop = ("RASTERSERVER_", "PYTHONPROFILEIMPORTTIME")
    return {k: v for k, v in os.environ.items() if not k.startswith(drop)}


@pytest.fixture(scope="module")
def archive(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An archive (SQLite catalogue) with one simulated acquisition, processed."""
    from rasterserver.demo import simulate_visits
    from rasterserver.optics import default_station
    from rasterserver.pipeline import Pipeline
    from rasterserver.simulated_visits import archive_visits

    root = tmp_path_factory.mktemp("cli-imports") / "archive"
    done = run_installed("db", "upgrade", archive=root)
    assert done.returncode == 0, describe(done)
    with Archive(Settings(archive=root, database_url=sqlite_url(root))) as opened:
        (acq,) = archive_visits(
            opened, simulate_visits(1, supersample=1), station=default_station(), patient="P1"
        )
        Pipeline(opened).process(acq.uid)
    return root


def hooked(args: list[str], tmp_path: Path) -> tuple[int, list[str]]:
    """Run ``rasterserver ARGS`` in-process in a fresh interpreter: exit code, modules."""
    report = tmp_path / "modules.json"
    done = subprocess.run(
        [sys.executable, "-c", HOOK, str(report), *args],
        capture_output=True, text=True, timeout=300, check=False, env=clean_env(),
        cwd=tmp_path,
    )
    assert report.exists(), f"the hook did not report\n{done.stdout}\n{done.stderr}"
    result = json.loads(report.read_text())
    return result["exit"], result["modules"]


def imported_by_installed(args: list[str], tmp_path: Path) -> tuple[int, str, list[str]]:
    """Run the installed ``rasterserver ARGS`` with the import log on: exit, stdout, modules."""
    done = subprocess.run(
        [installed_command(), *args],
        capture_output=True, text=True, timeout=300, check=False,
        env={**clean_env(), "PYTHONPROFILEIMPORTTIME": "1"}, cwd=tmp_path,
    )
    # "import time: <self us> | <cumulative us> | <indented module name>"
    modules = [
        line.rsplit("|", 1)[1].strip()
        for line in done.stderr.splitlines()
        if line.startswith("import time:") and line.count("|") == 2
    ]
    assert "rasterserver.cli" in modules, f"no import log read\n{done.stderr[-3000:]}"
    return done.returncode, done.stdout, modules


COMMANDS = {
    "help": ["--help"],
    "list": ["list"],
    "list-json": ["list", "--json"],
    "verify": ["verify"],
    "list-help": ["list", "--help"],
    "verify-help": ["verify", "--help"],
}


def _with_archive(args: list[str], archive: Path) -> list[str]:
    return args if args == ["--help"] else ["--archive", str(archive), *args]


@pytest.mark.parametrize("name", COMMANDS)
def test_in_process_sys_modules(name: str, archive: Path, tmp_path: Path) -> None:
    code, modules = hooked(_with_archive(COMMANDS[name], archive), tmp_path)
    assert code == 0
    assert not forbidden(modules), f"{name} loaded {forbidden(modules)}"


@pytest.mark.parametrize("name", ["help", "list", "verify"])
def test_installed_command_import_log(name: str, archive: Path, tmp_path: Path) -> None:
    code, out, modules = imported_by_installed(_with_archive(COMMANDS[name], archive), tmp_path)
    assert code == 0, out
    assert not forbidden(modules), f"{name} loaded {forbidden(modules)}"
    if name == "list":
        assert "P1" in out  # the acquisition was listed: the command did its work
    if name == "verify":
        assert "stored results: OK" in out


def test_help_does_not_load_the_archive_stack(tmp_path: Path) -> None:
    """``--help`` needs Typer and the command modules, not the catalogue, HDF5 or NumPy."""
    code, modules = hooked(["--help"], tmp_path)
    assert code == 0
    heavy = ("sqlalchemy", "alembic", "h5py", "numpy", "cv2", "rasterserver.archive",
             "rasterserver.ingest", "rasterserver.integrity", "rasterserver.catalog.catalog",
             "rasterserver.hashing")
    loaded = sorted(m for m in modules if m.split(".")[0] in heavy or m in heavy)
    assert not loaded, loaded


#: What ``list`` does without since issue 17: it opens the catalogue alone (a Catalog, no
#: Archive and file stores), reads it with SQLAlchemy Core (no ORM, no models) and checks the
#: schema revision without Alembic.
LIST_NEEDS_NOT = ("sqlalchemy.orm", "rasterserver.catalog.models", "rasterserver.archive",
                  "rasterserver.store.raw", "alembic", "numpy", "h5py", "cv2")


@pytest.mark.parametrize("name", ["list", "list-json"])
def test_list_reads_the_catalogue_alone(name: str, archive: Path, tmp_path: Path) -> None:
    code, modules = hooked(_with_archive(COMMANDS[name], archive), tmp_path)
    assert code == 0
    loaded = sorted(m for m in modules
                    if any(m == n or m.startswith(n + ".") for n in LIST_NEEDS_NOT))
    assert not loaded, loaded
    assert "rasterserver.catalog.listing" in modules


def test_verify_checks_the_schema_without_alembic(archive: Path, tmp_path: Path) -> None:
    code, modules = hooked(_with_archive(COMMANDS["verify"], archive), tmp_path)
    assert code == 0
    assert "rasterserver.integrity" in modules
    assert not [m for m in modules if m == "alembic" or m.startswith("alembic.")]


def test_the_hook_sees_a_heavy_import(tmp_path: Path) -> None:
    """Guard: the checks would see a forbidden package if a command loaded one."""
    code, modules = hooked(["simulate", "back", "--out", str(tmp_path / "out"),
                            "--width", "64", "--height", "64", "--supersample", "1"], tmp_path)
    assert code == 0
    assert "rasterserver.simulator" in forbidden(modules)


def test_copies_kept_for_a_light_start_agree() -> None:
    """What the command modules hold apart from the heavy modules is the same thing."""
    from rasterserver import export, export_choices, registry
    from rasterserver.commands import plugins

    assert plugins.STAGE_GROUP == registry.STAGE_GROUP
    assert export.ExportFormat is export_choices.ExportFormat
    assert export.ExportWhat is export_choices.ExportWhat
    assert export.ExportFrame is export_choices.ExportFrame


#: Command modules each command may load: its own (and the light helpers they share).
_SHARED = {"rasterserver.commands.light_params"}
OWN_MODULES = {
    "help": _SHARED,
    "list": {*_SHARED, "rasterserver.commands.listing", "rasterserver.commands.common"},
    "verify": {*_SHARED, "rasterserver.commands.verify", "rasterserver.commands.common",
               "rasterserver.commands.progress"},
}


@pytest.mark.parametrize("name", OWN_MODULES)
def test_a_command_builds_itself_alone(name: str, archive: Path, tmp_path: Path) -> None:
    """The lazy root group imports the module of the command run and no other; neither the
    runner nor Pydantic (Typer's option coercion) loads for ``--help`` or ``list``."""
    code, modules = hooked(_with_archive(COMMANDS[name], archive), tmp_path)
    assert code == 0
    commands = {m for m in modules if m.startswith("rasterserver.commands.")}
    assert commands <= OWN_MODULES[name], sorted(commands - OWN_MODULES[name])
    assert "rasterserver.runner" not in modules
    if name != "verify":
        assert not [m for m in modules if m == "pydantic" or m.startswith("pydantic.")]
