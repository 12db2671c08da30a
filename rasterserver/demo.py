"""The main job on the embedded default: a simulated patient followed over several visits.

``rasterserver demo`` renders a progressing scoliosis (one rasterstereograph per visit, six
months apart) with the project's simulator, ingests the frames into the archive (SQLite and a
local folder by default), processes every acquisition through the registered stage plugins
(mesh and back-shape analysis), exports a mesh and a one-page report per visit, compares the
visits (registration, distance maps, trends: ``rasterserver compare``), verifies the archive
and ends with the key clinical parameters of every visit side by side — the whole
path a clinic's data takes, on a fresh machine, with one command.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from rasterserver.analysis import acquisition_analysis, parameter_columns
from rasterserver.archive import Archive
from rasterserver.catalog.models import Acquisition
from rasterserver.config import Settings
from rasterserver.export import write_mesh
from rasterserver.jobs import JobOutcome, process_many
from rasterserver.optics import default_station
from rasterserver.pipeline import DEFAULT_TARGETS, Pipeline
from rasterserver.records_surface import MeshRecord
from rasterserver.simulated_visits import SimulatedVisit, archive_visits, progressed
from rasterserver.simulator.back import make_back, preset
from rasterserver.simulator.render import RenderSettings, render

DEMO_PATIENT = "DEMO-0001"
DEMO_STATION = "demo-station"


@dataclass
class DemoResult:
    """What the demo did."""

    acquisitions: list[Acquisition]
    outcomes: list[JobOutcome]
    meshes: list[Path] = field(default_factory=list)
    reports: list[Path] = field(default_factory=list)
    #: each visit's ``parameters`` (:meth:`rasterserver.analysis.Analysis.document`), or None
    #: when its analysis found nothing
    parameters: list[dict | None] = field(default_factory=list)
    #: the folder of the visits' comparison report, None when it could not be made
    comparison: Path | None = None
    verified_frames: int = 0
    problems: int = 0


def simulate_visits(
    visits: int, *, progression: float = 0.25, supersample: int = 2, seed: int = 0
) -> list[SimulatedVisit]:
    """Render ``visits`` rasterstereographs of a moderate scoliosis that progresses.

    Parameters
    ----------
    visits : int
        Number of visits.
    progression : float
        Relative growth of the curves per visit.
    supersample : int
        Sub-samples per pixel side of the renderer.
    seed : int
        Noise seed of the first visit (later visits add their index).

    Returns
    -------
    list of SimulatedVisit
    """
    station = default_station()
    settings = RenderSettings(supersampling=supersample)
    out = []
    for visit in range(visits):
        params = progressed(preset("moderate"), visit, progression)
        rendering = render(make_back(params), station, settings=settings, seed=seed + visit)
        out.append(SimulatedVisit(params, rendering.image))
    return out


def run_demo(
    settings: Settings,
    *,
    visits: int = 3,
    export_dir: Path | None = None,
    log: Callable[[str], None] = print,
) -> DemoResult:
    """Simulate, ingest, process, export, report and verify a demo patient's visits.

    Parameters
    ----------
    settings : Settings
        Where the archive and catalogue are (SQLite inside the archive by default).
    visits : int
        How many visits to simulate.
    export_dir : Path, optional
        Where the meshes and reports go; default ``<archive>/exports``.
    log : callable
        Where progress lines go (no patient data).

    Returns
    -------
    DemoResult
    """
    export_dir = export_dir or settings.archive / "exports"
    log(f"simulating {visits} visit(s) of a progressing moderate scoliosis")
    simulated = simulate_visits(visits)
    with Archive.create(settings) as archive:
        acquisitions = archive_visits(
            archive,
            simulated,
            station=default_station(),
            patient=DEMO_PATIENT,
            station_name=DEMO_STATION,
            log=log,
        )
        uids = [a.uid for a in acquisitions]
        outcomes = process_many(archive, uids, until=DEFAULT_TARGETS)
        result = DemoResult(acquisitions, outcomes)
        pipeline = Pipeline(archive)
        export_dir.mkdir(parents=True, exist_ok=True)
        for i, outcome in enumerate(outcomes):
            if outcome.status != "done":
                log(f"visit {i + 1}: processing failed: {outcome.error}")
                continue
            _row, mesh = pipeline.result(outcome.uid, "mesh")
            assert isinstance(mesh, MeshRecord)
            path = export_dir / f"{DEMO_PATIENT}-visit-{i + 1:02d}.ply"
            write_mesh(mesh, path, fmt="ply")
            result.meshes.append(path)
            log(
                f"visit {i + 1}: processed ({outcome.computed} stages computed, "
                f"{outcome.reused} reused); mesh of {len(mesh.vertices)} vertices -> {path}"
            )
            result.parameters.append(_report(pipeline, outcome.uid, i, export_dir, result, log))
        done = [o.uid for o in outcomes if o.status == "done"]
        if len(done) >= 2:
            result.comparison = _compare(pipeline, done, export_dir, log)
        report = archive.verify()
        derived = pipeline.verify()
        result.verified_frames = report.frames_checked
        result.problems = len(report.problems) + len(derived.problems)
        log(
            f"verify: {report.acquisitions_checked} acquisitions, {report.frames_checked} "
            f"frames, {derived.frames_checked} stored results, {result.problems} problem(s)"
        )
    columns = [(f"visit {i + 1}", p) for i, p in enumerate(result.parameters)]
    if any(p for _h, p in columns):
        log("back-shape parameters (docs/analysis.md):")
        for line in parameter_columns(columns):
            log("  " + line)
    return result


def _compare(
    pipeline: Pipeline, uids: list[str], export_dir: Path, log: Callable[[str], None]
) -> Path | None:
    """Compare the visits (consecutive ones and first with last) into ``export_dir``.

    A rerun replaces the demo's earlier comparison folder whole: the new one is written beside
    it first, so an interrupted demo leaves the old one in place.
    """
    import shutil

    from rasterserver.errors import InputError
    from rasterserver.visit_comparison import compare_visits

    final = export_dir / f"{DEMO_PATIENT}-comparison"
    fresh = export_dir / f".{DEMO_PATIENT}-comparison-new"
    shutil.rmtree(fresh, ignore_errors=True)
    try:
        document = compare_visits(pipeline, uids, fresh)
    except InputError as exc:
        log(f"comparison of the visits not made: {exc}")
        return None
    shutil.rmtree(final, ignore_errors=True)
    fresh.rename(final)
    for pair in document["pairs"]:
        if "refused" in pair:
            log(f"comparison {pair['a'][:8]} -> {pair['b'][:8]}: refused: {pair['refused']}")
            continue
        stats = pair["distance"]
        log(
            f"comparison {pair['a'][:8]} -> {pair['b'][:8]}: distance rms "
            f"{stats['rms_mm']:.1f} mm, largest {stats['max_abs_mm']:+.1f} mm"
        )
    log(f"comparison of the visits (report.html, distance maps, trends) -> {final}")
    return final


def _report(
    pipeline: Pipeline,
    uid: str,
    visit: int,
    export_dir: Path,
    result: DemoResult,
    log: Callable[[str], None],
) -> dict | None:
    """Write visit ``visit``'s report beside its mesh; its parameters, None if refused."""
    from rasterserver.analysis_report import write_report
    from rasterserver.errors import InputError

    try:
        analysis = acquisition_analysis(pipeline, uid, surfaces=True).check()
    except InputError as exc:  # the analysis found nothing: say why, go on
        log(f"visit {visit + 1}: {exc}")
        return None
    path = export_dir / f"{DEMO_PATIENT}-visit-{visit + 1:02d}-report.png"
    write_report(analysis, path, header=[f"visit {visit + 1}", f"acquisition {uid}"])
    result.reports.append(path)
    log(f"visit {visit + 1}: back-shape report -> {path}")
    return analysis.document()["parameters"]
