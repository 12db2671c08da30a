"""``rasterserver.chain_diff``: the stored results of two chains compared, on a chain changed
on purpose (the peak detector's bias fraction); the chain strings; the written report."""

from __future__ import annotations

import json
from pathlib import Path

import geometry_truth as gt
import numpy as np
import pytest

from rasterserver.archive import Archive
from rasterserver.chain_diff import diff_chains, renumbering, surface_displacement
from rasterserver.chain_diff_report import summary_lines, write_report
from rasterserver.chain_spec import parse_chain
from rasterserver.config import Settings, sqlite_url
from rasterserver.errors import InputError
from rasterserver.pipeline import Pipeline
from rasterserver.processing_jobs import Selection, resolve_selection
from rasterserver.records_lines import NumberedLines
from rasterserver.records_surface import Surface

#: A parameter that moves every peak of a real back and finds nothing in a black frame.
CHANGED = "peaks.bias_fraction=0.3"


def two_chains(settings: Settings) -> tuple[Archive, dict[str, str]]:
    """Two backs and a black frame processed with the default chain and with CHANGED."""
    image = gt.rendering("back").image
    frames = {"back0": image, "back1": np.roll(image, 3, axis=1),
              "black0": np.zeros_like(image)}
    archive, uids = gt.archive_with_frames(settings, frames)
    pipeline = Pipeline(archive)
    for uid in uids.values():
        for until in ("mesh", "analysis"):
            pipeline.process(uid, until=until)
            pipeline.process(uid, until=until, params={"peaks": {"bias_fraction": 0.3}})
    return archive, uids


@pytest.fixture(scope="module")
def processed(tmp_path_factory: pytest.TempPathFactory) -> tuple[Settings, dict[str, str]]:
    root = tmp_path_factory.mktemp("diff") / "archive"
    settings = Settings(archive=root, database_url=sqlite_url(root))
    archive, uids = two_chains(settings)
    archive.close()
    return settings, uids


def test_the_changed_acquisitions_and_only_they_are_named(processed, tmp_path: Path) -> None:
    settings, uids = processed
    with Archive(settings) as archive:
        selected = resolve_selection(archive, Selection(all=True))
        report = diff_chains(archive, parse_chain("default"), parse_chain(CHANGED), selected)
    assert sorted(report.by_status("changed")) == sorted([uids["back0"], uids["back1"]])
    assert report.by_status("unchanged") == [uids["black0"]]
    for acquisition in report.acquisitions:
        if acquisition.status == "changed":
            assert acquisition.changed_stages[0] == "peaks"
            assert {"mesh", "analysis", "surface"} <= set(acquisition.changed_stages)
            assert 0 < acquisition.displacement["p95_abs"] < 2.0  # a sub-pixel shift of peaks
            assert acquisition.numbering["peaks_matched"] > 1000
            assert acquisition.parameters and all(
                p["shift"] is not None for p in acquisition.parameters.values()
                if p["a"] is not None and p["b"] is not None)
    summary = report.summary()
    assert summary["changed"] == 2 and summary["unchanged"] == 1
    worst = {case["uid"] for case in summary["worst"]["displacement_p95_mm"]}
    assert worst == {uids["back0"], uids["back1"]}

    written = write_report(report, tmp_path / "out")
    assert {p.name for p in written} == {"diff.json", "displacement.png", "renumbering.png",
                                          "coverage.png", "parameters.png"}
    data = json.loads((tmp_path / "out" / "diff.json").read_text())
    assert data["summary"]["changed"] == 2 and len(data["acquisitions"]) == 3
    assert all(p.stat().st_size > 1000 for p in written)
    text = "\n".join(summary_lines(report))
    assert "2 changed, 1 unchanged" in text and uids["back0"] in text


def test_a_chain_compared_with_itself_changes_nothing(processed) -> None:
    settings, uids = processed
    with Archive(settings) as archive:
        selected = resolve_selection(archive, Selection(uids=tuple(uids.values())))
        report = diff_chains(archive, parse_chain(CHANGED), parse_chain(CHANGED), selected)
        pinned = diff_chains(archive, parse_chain("peaks=peaks.first-moment@0"),
                             parse_chain("default"), selected)
    assert report.by_status("unchanged") == list(uids.values())
    # no result of a version never run: nothing to compare with
    assert pinned.by_status("missing-a") == list(uids.values())


def test_chain_strings() -> None:
    spec = parse_chain("peaks=peaks.first-moment@3, peaks.bias_fraction=0.2,"
                       "numbers.mode=fast")
    assert spec.stages == {"peaks": "peaks.first-moment"}
    assert spec.versions == {"peaks": "3"}
    assert spec.params == {"peaks": {"bias_fraction": 0.2}, "numbers": {"mode": "fast"}}
    assert parse_chain("default").stages == {} and parse_chain("").text == "default"
    for bad in ("peaks", "peaks=", "=x", "peaks=a@", ".x=1", "peaks=a,peaks=b"):
        with pytest.raises(InputError):
            parse_chain(bad)
    with pytest.raises(InputError, match="installed version"):
        spec.to_process()


def test_surface_displacement_lines_up_shifted_grids() -> None:
    z = np.arange(12.0).reshape(3, 4)
    a = Surface(x0=0.0, y0=0.0, spacing=5.0, z=z)
    shifted = np.full((3, 4), np.nan)
    shifted[:, :3] = z[:, 1:] + 0.5  # the same cells, one column to the right, 0.5 mm deeper
    b = Surface(x0=5.0, y0=0.0, spacing=5.0, z=shifted)
    displacement, coverage = surface_displacement(a, b)
    assert displacement["cells"] == 9
    assert displacement["mean"] == pytest.approx(0.5) and displacement["max_abs"] == 0.5
    assert coverage["lost_cm2"] == pytest.approx(3 * 0.25) and coverage["gained_cm2"] == 0


def test_renumbering_counts_lines_whose_number_moved() -> None:
    def lines(numbers: list[int], rows: list[float]) -> NumberedLines:
        n = len(numbers)
        return NumberedLines(
            col=np.arange(n, dtype=np.int32), row=np.array(rows), area=np.ones(n, np.float32),
            height=np.ones(n, np.float32), width=np.full(n, 3, np.int16),
            image_shape=np.array([10, 10]), line_id=np.zeros(n, np.int32),
            order=np.zeros(n, np.int32), line_order=np.zeros(1, np.int32),
            line_component=np.zeros(1, np.int32), number=np.array(numbers, np.int32),
            line_number=np.array([numbers[0]], np.int32), kind_observed=np.zeros(1, np.int8),
            confidence=1.0, reason="")

    a = lines([5, 5, 5, 7], [1.0, 1.0, 1.0, 1.0])
    b = lines([6, 6, 5, -1], [1.2, 1.4, 3.0, 1.0])  # the third peak is two rows away
    counts = renumbering(a, b)
    assert counts["peaks_matched"] == 3 and counts["peaks_renumbered"] == 2
    assert counts["peaks_unnumbered"] == 1 and counts["lines_renumbered"] == 1
    assert counts["shifts"] == {"1": 1}
