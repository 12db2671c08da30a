"""Comparing two visits of one patient: registration, distance map, asymmetry map.

Pure functions of the records of two analysed acquisitions (a :class:`Visit` each: the
smoothed :class:`~rasterserver.records_surface.Surface`, its
:class:`~rasterserver.records_surface.MeshRecord` and its
:class:`~rasterserver.records_analysis.BackShape`); no archive, no files. Every position is in
the world frame of visit A's calibration (mm); visit B is moved onto it.

:func:`register`
    Visit B onto visit A: first B's body-fixed landmark frame (origin DM, axes from VP, DL,
    DR) mapped onto A's, then point-to-plane ICP (open3d) on the *trunk* of both, the part of
    the back between DM and VP inside the measured outline eroded by :data:`EDGE_MARGIN`
    (arms, head, buttocks and the ragged edges left out). Refused with a reason
    (:class:`ComparisonRefusedError`) when a landmark frame is missing or ICP does not
    converge within :data:`THRESHOLDS`; never a guessed alignment.
:func:`distance_map`
    Signed distance along A's vertex normal from each trunk vertex of A's mesh to B's
    registered mesh: positive where B lies *posterior* of A (towards the camera: a rib hump
    that grew), negative where it lies anterior (flattened). NaN where B has no surface
    within :data:`MAX_DISTANCE` (no overlap), and where the visits hold their arms, hands or
    clothing otherwise (a region from the outline inwards differing by more than any change
    of the back: :func:`displaced_regions`).
:func:`asymmetry_map`
    One visit against its own mirror image about the symmetry plane (Komeili et al., Spine J
    15 (2015) 743-751): the back mirrored about the body frame's sagittal plane (through DM,
    normal the transverse axis), fitted onto the back by ICP (the plane of best symmetry),
    then the signed distance as above: positive where this side is more posterior than its
    mirror (the hump side), negative on the other side.
:func:`asymmetry_change`
    B's asymmetry map minus A's, on A's vertices (through the registration).
:func:`carry_vp`
    A visit's VP carried through the registration to a visit whose analysis refused its
    own (hair or a shadow over the nape), for the symmetry line and what is measured along it.

The package by concept: :mod:`.thresholds` (what is accepted, the refusal), :mod:`.visits`
(the records compared and produced), :mod:`.carried` (VP carried), :mod:`.geometry`,
:mod:`.trunk` (landmark frame and trunk), :mod:`.registration`, :mod:`.distances` and
:mod:`.displaced` (regions where the visits' arms, hands or clothing lie otherwise: not
compared).
"""

from __future__ import annotations

from rasterserver.comparison.carried import CARRY_REACH, CarriedVP, carry_vp
from rasterserver.comparison.displaced import displaced_regions
from rasterserver.comparison.distances import (
    asymmetry_change,
    asymmetry_fit,
    asymmetry_map,
    distance_map,
    signed_distances,
)
from rasterserver.comparison.geometry import vertex_areas
from rasterserver.comparison.registration import register
from rasterserver.comparison.thresholds import (
    AXIS_WINDOW,
    EDGE_MARGIN,
    MAX_DISTANCE,
    THRESHOLDS,
    ComparisonRefusedError,
    Thresholds,
)
from rasterserver.comparison.trunk import (
    TOP_MARGIN,
    TrunkFrame,
    frame_transform,
    landmark_frame,
    landmark_transform,
    measured_height,
    pair_frames,
    submesh,
    trunk_frame,
    trunk_mask,
    trunk_mesh,
)
from rasterserver.comparison.visits import BodyFrame, DistanceMap, Registration, Visit

__all__ = [
    "AXIS_WINDOW",
    "CARRY_REACH",
    "EDGE_MARGIN",
    "MAX_DISTANCE",
    "THRESHOLDS",
    "TOP_MARGIN",
    "BodyFrame",
    "CarriedVP",
    "ComparisonRefusedError",
    "DistanceMap",
    "Registration",
    "Thresholds",
    "TrunkFrame",
    "Visit",
    "asymmetry_change",
    "asymmetry_fit",
    "asymmetry_map",
    "carry_vp",
    "displaced_regions",
    "distance_map",
    "frame_transform",
    "landmark_frame",
    "landmark_transform",
    "measured_height",
    "pair_frames",
    "register",
    "signed_distances",
    "submesh",
    "trunk_frame",
    "trunk_mask",
    "trunk_mesh",
    "vertex_areas",
]
