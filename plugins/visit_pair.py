"""The comparison stage: two visits of one patient registered, their difference mapped.

The first stage kind whose input comes from more than one acquisition: the service
(:mod:`rasterserver.stored_comparison`) assembles a
:class:`~rasterserver.records_comparison.VisitPair` from each acquisition's stored mesh,
surface outline and analysis, and stores the output with the input results' ids as its
provenance, so a comparison is computed once per pair of inputs and reused after. The
method (landmark frames, then robust point-to-plane ICP on the trunk; signed distance along
A's normals; mirror images for the asymmetry maps) is :mod:`rasterserver.comparison`'s and is
described in ``docs/comparison.md``.
"""

from __future__ import annotations

from dataclasses import replace

from pydantic import Field

from rasterserver.comparison import EDGE_MARGIN, THRESHOLDS
from rasterserver.pair_comparison import compare_pair
from rasterserver.records_comparison import ComparisonRecord, VisitPair
from rasterserver.stage import Stage, StageContext, StageParams

__all__ = ["LandmarkIcpComparison"]


class LandmarkIcpComparison(Stage[VisitPair, ComparisonRecord]):
    """Landmark frames, then robust point-to-plane ICP on the trunk; distance and asymmetry
    maps."""

    name = "comparison.landmark-icp"
    stage = "comparison"
    version = "1"
    input_type = VisitPair
    output_type = ComparisonRecord

    class Params(StageParams):
        margin: float = Field(
            EDGE_MARGIN, gt=0.0, le=100.0, description="Outline erosion of the trunk (mm)."
        )
        robust_scale: float = Field(
            THRESHOLDS.robust_scale or 1.0,
            gt=0.0,
            le=50.0,
            description="Scale of Tukey's biweight in the fine ICP pass (mm).",
        )
        voxel: float = Field(
            THRESHOLDS.voxel or 4.0,
            gt=0.0,
            le=50.0,
            description="Voxel the moved trunk is thinned to for ICP (mm).",
        )

    def run(self, data: VisitPair, params: Params, context: StageContext) -> ComparisonRecord:
        """Compare the two visits; a refusal is a record with its reason."""
        thresholds = replace(THRESHOLDS, robust_scale=params.robust_scale, voxel=params.voxel)
        return compare_pair(data, thresholds=thresholds, margin=params.margin)
