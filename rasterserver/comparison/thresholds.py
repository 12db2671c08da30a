"""What a comparison accepts: the trunk margin, the farthest distance reported, the
convergence bounds of the registration, and the refusal when they are not met."""

from __future__ import annotations

from dataclasses import dataclass

from rasterserver.errors import InputError

#: How far inside the measured outline the trunk starts (mm): the outermost cells of a
#: reconstructed surface are the least certain (grazing raster lines, smoothing at the rim).
EDGE_MARGIN = 15.0
#: Largest distance a distance map reports (mm); farther, the vertex has no counterpart.
MAX_DISTANCE = 30.0
#: Half-width (mm) of the band about the DM–VP line that a row's run of the measured outline
#: must reach to be trunk: wide enough for a scoliotic back's midline (2-3 cm off the line)
#: and a hole or two along the spine, far narrower than the back (the arms start 15-20 cm out).
AXIS_WINDOW = 40.0


@dataclass(frozen=True)
class Thresholds:
    """When a registration is accepted; values of :data:`THRESHOLDS` and why.

    Attributes
    ----------
    coarse_distance : float
        Correspondence distance of the first ICP pass (mm): the landmark frames agree to a few
        millimetres and about a degree (7 mm over a 440 mm trunk), so 20 mm catches them.
    fine_distance : float
        Correspondence distance of the second pass and of the reported fitness and rmse (mm).
    min_fitness : float
        Fraction of B's trunk points with a counterpart on A within ``fine_distance``: below
        0.7 the two surfaces do not overlap enough to say they were aligned.
    max_rmse : float
        Inlier rmse (mm); two visits of one back agree to well under 1 mm after
        registration, a progressed scoliosis to 2-3 mm; above 4 mm the alignment is not
        trusted.
    max_shift : float
        Largest distance (mm) ICP may move the trunk's centre away from where the landmark
        frames put it; farther means ICP slid into another minimum.
    max_turn : float
        Largest rotation (degrees) ICP may add to the landmark frames' rotation.
    min_points : int
        Fewest trunk points of either visit.
    robust_scale : float or None
        Scale (mm) of Tukey's biweight in the fine ICP pass: point-to-plane residuals beyond
        it do not pull the alignment (a changed region is left out of the fit). Two renders
        of one back agree to about 0.1 mm along the normal, a change worth mapping is
        millimetres. None: plain least squares.
    voxel : float or None
        Voxel size (mm) the moved visit's trunk is thinned to for ICP (one point per voxel,
        their mean); None: every point.
    mirror_distance : float
        Correspondence distance (mm) of the asymmetry map's mirror fit, both passes.
    mirror_reach : float or None
        The mirror fit uses only the trunk points whose mirror image about the landmarks'
        plane lies within this distance (mm) of the measured trunk: the points seen alike
        on both sides. Arms held away, a hole on one side or clothing otherwise let the
        fit slide into another minimum as its inliers change (tuning person 44: the plane
        turned 5.7° and moved 7 mm between two acquisitions of one back). None: every
        trunk point (asymmetry version 3).
    displaced_limit : float or None
        Difference (mm) beyond which a region of the distance map reaching the trunk's
        outline is not compared (:func:`~rasterserver.comparison.displaced_regions`: arms,
        hands or clothing placed otherwise); a back changes between visits by millimetres
        (the moderate preset's main curve turned by +4° and moved by +7 mm: 12 mm at most),
        an arm moved differs by 10-30 mm or has no counterpart. None: every vertex compared
        (version 1).
    displaced_slope : float
        Change of the difference along the surface (mm per mm) that joins such a region: the
        ramp from the trunk onto an arm (a changed back's difference changes slowly).
    displaced_margin : float
        Band (mm) around such a region also not compared.
    axis_window : float or None
        :func:`~rasterserver.comparison.trunk_mask`'s ``window``: in each row only the runs
        of the outline reaching this close to the DM–VP line are trunk (arms apart from it in
        the row left out); None: the connected piece (version 1).
    partial_frame : bool
        Register a visit whose VP was not found from DM, DL → DR and the station's vertical
        (:func:`~rasterserver.comparison.pair_frames`); False refuses it (version 1).
    frame_without_vp : bool
        With ``partial_frame``, also register two visits neither of which has its VP (the
        trunk compared as high as both measure it below the neck); False refuses them
        (version 2).
    through_slack : float or None
        The distance map's hit along A's normal that lies more than twice as far as B's
        nearest point and farther by more than this (mm) went through a hole of B's surface
        to another part of it (:func:`~rasterserver.comparison.signed_distances`): not
        compared. None: every hit kept (comparison version 3). The asymmetry map applies it
        to the mirror image's holes (asymmetry version 3; None is its version 2).
    """

    coarse_distance: float = 20.0
    fine_distance: float = 5.0
    min_fitness: float = 0.7
    max_rmse: float = 4.0
    max_shift: float = 25.0
    max_turn: float = 8.0
    min_points: int = 500
    robust_scale: float | None = 1.0
    voxel: float | None = 4.0
    mirror_distance: float = 10.0
    mirror_reach: float | None = 10.0
    displaced_limit: float | None = 15.0
    displaced_slope: float = 0.2
    displaced_margin: float = 20.0
    axis_window: float | None = AXIS_WINDOW
    partial_frame: bool = True
    frame_without_vp: bool = True
    through_slack: float | None = 3.0


#: The thresholds :func:`register` uses unless given others.
THRESHOLDS = Thresholds()


class ComparisonRefusedError(InputError):
    """Two visits cannot be compared; the message says why (exit 2, HTTP 422)."""
