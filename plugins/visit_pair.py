"""The comparison and asymmetry stages: visits of one patient registered, their difference
and each visit's asymmetry mapped.

The first stage kind whose input comes from more than one acquisition: the service
(:mod:`rasterserver.stored_comparison`) assembles a
:class:`~rasterserver.records_comparison.VisitPair` from each acquisition's stored mesh,
surface outline and analysis, and stores the output with the input results' ids as its
provenance, so a comparison is computed once per pair of inputs and reused after. The
method (landmark frames, then robust point-to-plane ICP on the trunk; signed distance along
A's normals; mirror images for the asymmetry maps) is :mod:`rasterserver.comparison`'s and is
described in ``docs/comparison.md``. The asymmetry map is a stage of its own (input: one
visit) so that it is computed once per visit, not once per pair the visit is part of.
"""

from __future__ import annotations

from dataclasses import replace

from pydantic import Field

from rasterserver.comparison import AXIS_WINDOW, EDGE_MARGIN, THRESHOLDS
from rasterserver.pair_comparison import compare_pair, visit_asymmetry
from rasterserver.records_comparison import (
    AsymmetryRecord,
    ComparisonRecord,
    VisitGeometry,
    VisitPair,
)
from rasterserver.stage import Stage, StageContext, StageParams

__all__ = ["LandmarkIcpComparison", "MirrorIcpAsymmetry"]

_WINDOW = (
    "Half-width (mm) of the band about the DM-VP line that a row's run of the outline must "
    "reach to be trunk (arms apart from the trunk in the row left out); 0: the connected "
    "piece of the outline (version 1)."
)


class LandmarkIcpComparison(Stage[VisitPair, ComparisonRecord]):
    """Landmark frames, then robust point-to-plane ICP on the trunk; distance and asymmetry
    maps."""

    name = "comparison.landmark-icp"
    stage = "comparison"
    # 2: the trunk's rows, displaced regions, a visit without VP framed from its dimples
    # 3: two visits without VP framed from their dimples, the trunk as high as both measure it
    # 4: the distance map's hits through a hole of B's surface (to another part of it) are no
    #    counterparts
    version = "4"
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
        displaced_limit: float = Field(
            THRESHOLDS.displaced_limit or 15.0,
            ge=0.0,
            le=30.0,
            description=(
                "Difference (mm) beyond which a region of the distance map reaching the "
                "trunk's outline is not compared (arms, hands or clothing placed otherwise); "
                "0 compares every vertex (version 1)."
            ),
        )
        displaced_slope: float = Field(
            THRESHOLDS.displaced_slope,
            gt=0.0,
            le=10.0,
            description="Change of the difference along the surface (mm/mm) joining a region.",
        )
        displaced_margin: float = Field(
            THRESHOLDS.displaced_margin,
            ge=0.0,
            le=100.0,
            description="Band (mm) around such a region also not compared.",
        )
        axis_window: float = Field(AXIS_WINDOW, ge=0.0, le=200.0, description=_WINDOW)
        partial_frame: bool = Field(
            True,
            description=(
                "Register a visit whose VP was not found from DM, DL -> DR and the station's "
                "vertical (the analysis's gravity), the trunk as high as the other visit's; "
                "false refuses it (version 1)."
            ),
        )
        frame_without_vp: bool = Field(
            True,
            description=(
                "With partial_frame, also register two visits neither of which has its VP "
                "(the same hair over the nape), the trunk compared as high as both visits "
                "measure it below the neck, less 40 mm; false refuses them (version 2)."
            ),
        )
        through_slack: float = Field(
            THRESHOLDS.through_slack or 3.0,
            ge=0.0,
            le=30.0,
            description=(
                "A hit along A's normal more than twice as far as B's nearest point and "
                "farther by more than this (mm) went through a hole of B's surface: not "
                "compared. 0 keeps every hit (version 3)."
            ),
        )

    def run(self, data: VisitPair, params: Params, context: StageContext) -> ComparisonRecord:
        """Compare the two visits; a refusal is a record with its reason."""
        thresholds = replace(
            THRESHOLDS,
            robust_scale=params.robust_scale,
            voxel=params.voxel,
            displaced_limit=params.displaced_limit or None,
            displaced_slope=params.displaced_slope,
            displaced_margin=params.displaced_margin,
            axis_window=params.axis_window or None,
            partial_frame=params.partial_frame,
            frame_without_vp=params.frame_without_vp,
            through_slack=params.through_slack or None,
        )
        return compare_pair(data, thresholds=thresholds, margin=params.margin)


class MirrorIcpAsymmetry(Stage[VisitGeometry, AsymmetryRecord]):
    """The back against its mirror image about the plane of best symmetry (Komeili et al.,
    Spine J 2015): mirrored about the body frame's sagittal plane, fitted by robust ICP."""

    name = "asymmetry.mirror-icp"
    stage = "asymmetry"
    # 3: a vertex whose normal passes through a hole of the mirror image to another part of
    #    it has no value (as the comparison's distance map since its version 4)
    # 4: the mirror fit uses only the trunk seen alike on both sides where the landmarks put
    #    the plane (mirror_reach), so that it cannot slide into another minimum
    version = "4"
    input_type = VisitGeometry
    output_type = AsymmetryRecord

    class Params(StageParams):
        margin: float = Field(
            EDGE_MARGIN, gt=0.0, le=100.0, description="Outline erosion of the trunk (mm)."
        )
        mirror_distance: float = Field(
            THRESHOLDS.mirror_distance,
            gt=0.0,
            le=50.0,
            description="Correspondence distance of the mirror fit (mm).",
        )
        axis_window: float = Field(AXIS_WINDOW, ge=0.0, le=200.0, description=_WINDOW)
        through_slack: float = Field(
            THRESHOLDS.through_slack or 3.0,
            ge=0.0,
            le=30.0,
            description=(
                "A hit along the back's normal more than twice as far as its mirror image's "
                "nearest point and farther by more than this (mm) went through a hole of the "
                "mirror image: no value there. 0 keeps every hit (version 2)."
            ),
        )
        mirror_reach: float = Field(
            THRESHOLDS.mirror_reach or 10.0,
            ge=0.0,
            le=50.0,
            description=(
                "The mirror fit uses only the trunk points whose mirror image about the "
                "landmarks' plane lies within this distance (mm) of the measured trunk (seen "
                "alike on both sides). 0 fits every trunk point (version 3)."
            ),
        )

    def run(self, data: VisitGeometry, params: Params, context: StageContext) -> AsymmetryRecord:
        """Map the visit's asymmetry; a refusal is a record with its reason."""
        thresholds = replace(
            THRESHOLDS,
            mirror_distance=params.mirror_distance,
            axis_window=params.axis_window or None,
            through_slack=params.through_slack or None,
            mirror_reach=params.mirror_reach or None,
        )
        return visit_asymmetry(data, thresholds=thresholds, margin=params.margin)
