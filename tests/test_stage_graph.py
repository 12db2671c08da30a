"""The stage graph: chains resolved by record types, so a plugin package can add a stage kind.

A third-party distribution is written into ``tmp_path`` as ``pip install`` would leave it (a
module and a ``*.dist-info`` with ``entry_points.txt``): a new kind ``relief`` that takes the
built-in ``Surface`` and gives a record type of its own. It must be found, run, stored with
provenance, reused and verified exactly like the built-in stages, in process and by the
installed ``rasterserver`` command in fresh processes.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import geometry_truth as gt
import pytest
from test_registry import write_distribution

from rasterserver.config import Settings, sqlite_url
from rasterserver.errors import InputError
from rasterserver.pipeline import Pipeline, resolve_chain
from rasterserver.registry import Registry
from rasterserver.stage import BUILTIN_STAGE_KINDS

RELIEF_MODULE = '''
"""A third-party analysis: the depth range of a surface, in a record type of its own."""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from rasterserver.records import Record
from rasterserver.records_surface import Surface
from rasterserver.stage import Stage, StageContext, StageParams


class Relief(Record):
    """Depth range of the measured cells."""

    kind: ClassVar[str] = "relief-stats"
    depth_range: float
    cells: int
    reason: str = ""


class DepthRange(Stage[Surface, Relief]):
    """Depth range (max - min) of a smoothed surface."""

    name = "relief.depth-range"
    stage = "relief"
    version = "1"
    input_type = Surface
    output_type = Relief

    def run(self, data: Surface, params: StageParams, context: StageContext) -> Relief:
        z = data.z[np.isfinite(data.z)]
        if z.size == 0:
            return Relief(depth_range=0.0, cells=0, reason="no measured cell")
        return Relief(depth_range=float(z.max() - z.min()), cells=int(z.size))
'''


@pytest.fixture
def relief_package(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """Install ``relief-plugin 0.3`` (kind ``relief``: Surface → relief-stats) on sys.path."""
    root = tmp_path / "site"
    root.mkdir()
    write_distribution(
        root,
        "relief-plugin",
        "0.3",
        {"relief.depth-range": "relief_plugin:DepthRange"},
        {"relief_plugin": RELIEF_MODULE},
    )
    monkeypatch.syspath_prepend(str(root))
    sys.modules.pop("relief_plugin", None)
    yield root
    sys.modules.pop("relief_plugin", None)


def test_chains_are_resolved_by_type_up_to_any_kind() -> None:
    registry = Registry().discover()
    assert [s.kind for s in resolve_chain(registry=registry)] == list(BUILTIN_STAGE_KINDS)
    analysis = resolve_chain(until="analysis", registry=registry)
    # the analysis takes the surface: the mesh is not on its way
    assert [s.kind for s in analysis] == [*BUILTIN_STAGE_KINDS[:6], "analysis"]
    with pytest.raises(InputError, match="unknown stage kind"):
        resolve_chain(until="no-such-kind", registry=registry)
    # a choice for a stage after the target is not run, and not an error
    steps = resolve_chain({"mesh": "mesh.grid"}, until="surface", registry=registry)
    assert steps[-1].kind == "surface"


def test_a_plugin_adds_a_kind_found_by_type(relief_package: Path) -> None:
    registry = Registry().discover()
    assert "relief" in registry.stage_kinds()
    steps = resolve_chain(until="relief", registry=registry)
    assert [s.kind for s in steps] == [*BUILTIN_STAGE_KINDS[:6], "relief"]
    assert steps[-1].package == "relief-plugin 0.3"
    graph = registry.graph()
    assert ("surface", "relief", "relief-stats") in {
        (e.input_kind, e.stage, e.output_kind) for e in graph
    }


def test_a_plugin_kind_is_stored_reused_and_reprocessed(
    relief_package: Path, settings: Settings
) -> None:
    archive, uids = gt.archive_with_frames(settings, {"back": gt.rendering("back").image})
    try:
        registry = Registry().discover()
        pipeline = Pipeline(archive, registry=registry)
        first = pipeline.process(uids["back"], until="relief")
        assert [s.kind for s in first.steps] == [*BUILTIN_STAGE_KINDS[:6], "relief"]
        assert first.final.kind == "relief-stats" and first.final.depth_range > 50
        row, record = pipeline.result(uids["back"], "relief")
        assert row.plugin == "relief.depth-range" and row.plugin_package == "relief-plugin 0.3"
        assert row.record_kind == "relief-stats" and record == first.final
        # the built-in chain reuses everything up to the surface, and the relief after it
        mesh = pipeline.process(uids["back"])
        assert mesh.reused == 6 and mesh.computed == 1
        again = pipeline.process(uids["back"], until="relief")
        assert again.computed == 0 and again.reused == 7
        assert pipeline.verify().ok
    finally:
        archive.close()


def test_the_installed_command_runs_and_verifies_a_plugin_kind(
    relief_package: Path, tmp_path: Path
) -> None:
    # fresh processes, as users run them: `plugins`, `process --until relief`, `verify`
    exe = Path(sys.executable).with_name("rasterserver")
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(relief_package), str(Path(__file__).parent)]),
        "RASTERSERVER_ARCHIVE": str(tmp_path / "archive"),
    }
    env.pop("RASTERSERVER_DATABASE_URL", None)
    settings = Settings(archive=tmp_path / "archive", database_url=sqlite_url(tmp_path / "archive"))
    archive, uids = gt.archive_with_frames(settings, {"back": gt.rendering("back").image})
    archive.close()

    def run(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [str(exe), *args], env=env, capture_output=True, text=True, timeout=300, check=False
        )

    listing = run("plugins", "--graph")
    assert listing.returncode == 0, listing.stderr
    assert "relief.depth-range" in listing.stdout and "relief-stats" in listing.stdout
    done = run("process", uids["back"], "--until", "relief")
    assert done.returncode == 0, done.stderr
    verify = run("verify")
    assert verify.returncode == 0, verify.stdout + verify.stderr
    assert "7 stored results: OK" in verify.stdout
