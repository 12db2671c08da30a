"""Optional extras (issue 17): a command whose extra is not installed names the extra to install
and exits 8, without a traceback; the extras in pyproject.toml and in rasterserver.extras agree,
and the `test` extra pulls all of them (CI installs ".[test]")."""

from __future__ import annotations

import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from rasterserver.errors import UnavailableError
from rasterserver.extras import EXTRAS, MissingExtraError, missing_extra

ROOT = Path(__file__).resolve().parents[1]
# distribution name in pyproject → the top-level module it installs
_MODULES = {"python-multipart": "python_multipart", "prometheus-client": "prometheus_client"}


def _extras() -> dict[str, list[str]]:
    with (ROOT / "pyproject.toml").open("rb") as fh:
        return tomllib.load(fh)["project"]["optional-dependencies"]


def _name(requirement: str) -> str:
    return re.split(r"[\[<>=;! ]", requirement, maxsplit=1)[0]


@pytest.mark.parametrize("extra", ["server", "dask"])
def test_every_package_of_an_extra_is_named_by_the_cli(extra: str) -> None:
    for requirement in _extras()[extra]:
        name = _name(requirement)
        module = _MODULES.get(name, name)
        assert EXTRAS.get(module, ("?",))[0] == extra, f"{module} missing from EXTRAS"


def test_the_test_extra_pulls_every_extra() -> None:
    extras = _extras()
    pulled = {
        e.strip()
        for r in extras["test"]
        if _name(r) == "rasterserver"
        for e in r[r.index("[") + 1 : r.index("]")].split(",")
    }
    assert pulled == set(extras) - {"test"}
    # and the core no longer lists what moved to an extra
    with (ROOT / "pyproject.toml").open("rb") as fh:
        core = {_name(r) for r in tomllib.load(fh)["project"]["dependencies"]}
    assert not core & {_name(r) for e in ("server", "dask") for r in extras[e]}


def _without(modules: list[str], argv: list[str], archive: Path) -> subprocess.CompletedProcess:
    """``rasterserver ARGV`` in a fresh interpreter where ``modules`` cannot be imported (a
    None entry in sys.modules is what Python does for an absent package: ModuleNotFoundError)."""
    code = (
        "import sys\n"
        f"for name in {modules!r}:\n"
        "    sys.modules[name] = None\n"
        "from rasterserver.cli import main\n"
        f"sys.exit(main({argv!r}))\n"
    )
    return subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=archive,
        env={"PATH": "/usr/bin:/bin", "RASTERSERVER_ARCHIVE": str(archive / "archive")},
    )


@pytest.mark.parametrize(
    "absent",
    [["uvicorn"], ["fastapi"]],
    ids=["without-uvicorn", "without-fastapi"],
)
def test_serve_without_the_server_extra_names_it(tmp_path: Path, absent: list[str]) -> None:
    done = _without(absent, ["serve", "--port", "8765"], tmp_path)
    assert done.returncode == 8, done.stderr
    assert "Traceback" not in done.stderr
    assert f"needs the package '{absent[0]}', which is not installed" in done.stderr
    assert "pip install 'rasterserver[server]'" in done.stderr
    assert done.stdout == ""


def test_the_light_commands_need_no_extra(tmp_path: Path) -> None:
    absent = ["fastapi", "uvicorn", "starlette", "dask", "distributed"]
    done = _without(absent, ["--help"], tmp_path)
    assert done.returncode == 0, done.stderr
    assert "serve" in done.stdout


def test_dask_without_the_dask_extra_names_it(monkeypatch: pytest.MonkeyPatch) -> None:
    from rasterserver.jobs import dask_client

    monkeypatch.setitem(sys.modules, "distributed", None)
    with pytest.raises(ModuleNotFoundError) as caught, dask_client(n_workers=1):
        pass
    found = missing_extra(caught.value)
    assert isinstance(found, MissingExtraError) and isinstance(found, UnavailableError)
    assert found.extra == "dask" and found.exit_code == 8
    assert "pip install 'rasterserver[dask]'" in str(found) and "--no-dask" in str(found)


def test_other_errors_are_not_taken_for_a_missing_extra() -> None:
    assert missing_extra(ModuleNotFoundError("no module", name="no_such_thing")) is None
    assert missing_extra(ValueError("x")) is None
    wrapped = RuntimeError("plugin failed")
    wrapped.__cause__ = ModuleNotFoundError("x", name="fastapi.routing")
    found = missing_extra(wrapped)
    assert found is not None and found.extra == "server" and found.module == "fastapi"


def test_process_with_dask_without_the_dask_extra_names_it(tmp_path: Path) -> None:
    """The real command on a real archive: `process --all --dask` where dask.distributed
    cannot be imported exits 8 with the extra to install (the job stays resumable)."""
    from rasterserver.archive import Archive
    from rasterserver.cli import main
    from rasterserver.config import Settings, sqlite_url
    from rasterserver.demo import simulate_visits
    from rasterserver.optics import default_station
    from rasterserver.simulated_visits import archive_visits

    root = tmp_path / "archive"
    settings = Settings(archive=root, database_url=sqlite_url(root))
    url = settings.database_url
    assert main(["--archive", str(root), "--database-url", url, "db", "upgrade"]) == 0
    with Archive(settings) as archive:
        archive_visits(
            archive, simulate_visits(1, supersample=1), station=default_station(), patient="P1"
        )
    done = _without(["distributed", "dask"], ["process", "--all", "--dask"], tmp_path)
    assert done.returncode == 8, done.stderr
    assert "Traceback" not in done.stderr
    assert "pip install 'rasterserver[dask]'" in done.stderr and "--no-dask" in done.stderr
