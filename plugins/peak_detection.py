"""Peak detection: the sub-pixel rows where raster lines cross each pixel column.

The seed's method, over the whole frame at once:

1. the extrema are found on the raw grey values of each column, as the seed finds them.
   Version 5 and earlier found them on a ``[1, 2, 1] / 4`` smoothed column (``smooth``),
   so that a noise wiggle would not split a peak; but where the back turns away from the
   camera two lines two or three pixels apart merged into one maximum there, and a dim
   narrow line fell under the least height. The heights, raised with the frame's noise
   (``noise_factor``), keep noise from making peaks instead;
2. a maximum is where the slope turns from positive to negative (zero slopes skipped, so a
   plateau belongs to the flank it continues); its pixels run from the nearest minimum on
   its left to the nearest minimum on its right (column ends count as minima), found for
   all maxima at once by a binary search in the sorted minima;
3. the peak is kept when its rise and fall are high enough (``min_height``, raised to
   ``noise_factor`` times the frame's pixel noise when that is more) and steep enough
   (``min_slope``: the height over the number of pixels above the bias on each flank, which
   rejects broad shading humps but keeps the broad dim lines of inclined skin);
4. a bias is subtracted: the larger of the two bounding minima, raised by ``bias_fraction``
   of the peak's height, which keeps background noise (always positive after clipping) out of
   the moment; only the contiguous run of pixels above the bias around the maximum counts;
5. row = first moment (intensity-weighted mean row) of the bias-subtracted pixels,
   area = their sum.

The extrema (step 2) and the runs and moments (steps 4-5) are scans compiled with numba
(:mod:`rasterserver_plugins.peak_scan`); the rest is whole-array numpy.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Literal

import cv2
import numpy as np
from pydantic import Field

from rasterserver.records import Image
from rasterserver.records_lines import Peaks
from rasterserver.stage import Stage, StageContext, StageParams

from .flanked_peaks import FlankRule, flanked
from .image_noise import noise_level

__all__ = ["VERSION_5", "FirstMomentPeaks", "PeakArrays", "detect_peaks"]

BiasMode = Literal["max-minimum", "min-minimum", "none"]

#: The parameters under which version 6 gives version 5's peaks (the extrema on smoothed
#: columns, the heights over 3.5 times the noise): the earlier version, for comparisons.
VERSION_5: dict[str, object] = {"smooth": True, "noise_factor": 3.5}

_SMOOTH = np.array([0.25, 0.5, 0.25], dtype=np.float32)
_ONE = np.array([1.0], dtype=np.float32)


@dataclass(frozen=True)
class PeakArrays:
    """Per-peak arrays as :func:`detect_peaks` returns them (the fields of :class:`Peaks`);
    ``dropped`` counts the peaks left out because their location cannot be trusted."""

    col: np.ndarray
    row: np.ndarray
    area: np.ndarray
    height: np.ndarray
    width: np.ndarray
    dropped: int = 0

    def to_record(self, image_shape: tuple[int, int]) -> Peaks:
        """Wrap the arrays in a :class:`~rasterserver.records_lines.Peaks` record."""
        return Peaks(
            col=self.col,
            row=self.row,
            area=self.area,
            height=self.height,
            width=self.width,
            image_shape=np.asarray(image_shape, dtype=np.int64),
            dropped=self.dropped,
        )


def _empty() -> PeakArrays:
    return PeakArrays(
        col=np.zeros(0, np.int32),
        row=np.zeros(0, np.float64),
        area=np.zeros(0, np.float32),
        height=np.zeros(0, np.float32),
        width=np.zeros(0, np.int16),
        dropped=0,
    )


def detect_peaks(
    image: np.ndarray,
    *,
    min_height: float = 3.0,
    min_slope: float = 2.0,
    bias: BiasMode = "max-minimum",
    bias_fraction: float = 0.1,
    min_width: int = 2,
    max_width: int = 25,
    smooth: bool = False,
    trust: bool = True,
    min_trust_height: float = 3.0,
    max_base_step: float = 0.4,
    max_flank_asymmetry: int = 1,
    clip_level: float | None = None,
    narrow: bool = True,
    noise_factor: float = 5.7,
    flank_rule: FlankRule | None = None,
) -> PeakArrays:
    """Find the raster-line peaks in every column of ``image``.

    Parameters
    ----------
    image : numpy.ndarray
        ``(H, W)`` grey values, any real dtype; raster lines run across the columns.
    min_height : float
        Least rise and fall (DN, on the column the extrema are found on) from the bounding
        minima to the maximum.
    min_slope : float
        Least mean slope (DN/px) of each flank above the bias: the peak's height over the
        number of pixels from the maximum to the flank's end. Scale it down for sensors
        whose peaks span more pixels.
    bias : {"max-minimum", "min-minimum", "none"}
        Base level subtracted before the moments: the larger or the smaller of the two
        bounding minima, or zero.
    bias_fraction : float
        Fraction of the peak's height above the base added to the bias.
    min_width : int
        Least number of contiguous pixels above the bias (rejects hot pixels).
    max_width : int
        Largest window considered around a maximum; longer runs of background are clipped
        to ``max_width // 2`` pixels each side. Set it to ~2.5 line spacings in pixels.
    smooth : bool
        Smooth the columns with ``[1, 2, 1] / 4`` to find the extrema (version 5 and
        earlier, with ``noise_factor`` 3.5).
    trust : bool
        Drop the peaks whose location cannot be trusted (the next four parameters); their
        number is returned in ``PeakArrays.dropped``.
    min_trust_height : float
        Least height above the bias (DN) of a trusted peak.
    max_base_step : float
        Largest difference of the two bounding minima, as a fraction of the height.
    max_flank_asymmetry : int
        Largest difference (px) of the lengths of the two flanks above the bias.
    clip_level : float, optional
        Grey value at which the sensor clips; a top at or above it over two pixels or more
        is clipped. By default the largest value of an integer image's type; none for a
        float image.
    narrow : bool
        Keep peaks narrower than ``min_width`` above the bias (lines sharper than a pixel),
        located by the centroid of the maximum and its two neighbours above the bounding
        minima; otherwise they are not found.
    noise_factor : float
        Raise ``min_height`` and ``min_trust_height`` to this many times the frame's pixel
        noise (:func:`~rasterserver_plugins.image_noise.noise_level`) where that is more:
        the heights are then floors for a quiet camera, and a noisy one does not fill the
        dark background with peaks. 0 uses the heights as given. 5.7 on the raw column
        is version 5's 3.5 on the smoothed one, whose noise the ``[1, 2, 1] / 4`` kernel
        lowers to 0.61 of the pixels' (3.5 on the raw column left 45-88 false peaks in a
        604 x 576 frame of pure noise; 5.7 leaves none, as 3.5 did on the smoothed one).
    flank_rule : FlankRule, optional
        Keep the peaks dropped for unequal minima or flanks only where trusted peaks of the
        same line flank them (:func:`~rasterserver_plugins.flanked_peaks.flanked`); by
        default none is kept.

    Returns
    -------
    PeakArrays
        Sorted by column, then row.
    """
    img = np.asarray(image)
    if img.ndim != 2:
        raise ValueError(f"image must be 2-D, got shape {img.shape}")
    h, w = img.shape
    if h < 3 or w < 1:
        return _empty()
    if noise_factor > 0:
        floor = noise_factor * noise_level(img)
        min_height = max(min_height, floor)
        min_trust_height = max(min_trust_height, floor)
    # Columns as contiguous rows of the transposed image: every pass below then streams
    # through memory, and a flat index walks column by column.
    if clip_level is None and img.dtype.kind in "iu":
        clip_level = float(np.iinfo(img.dtype).max)
    if img.dtype in (np.uint8, np.uint16) and img.dtype.isnative:
        t = cv2.transpose(img).astype(np.float32)  # 4x faster than numpy's strided copy
    else:
        t = np.ascontiguousarray(img.T, dtype=np.float32)
    s = cv2.sepFilter2D(t, -1, _SMOOTH, _ONE, borderType=cv2.BORDER_REPLICATE) if smooth else t
    # compiled scans (peak_scan); imported on first use, the numba import costs ~0.3 s
    from .peak_scan import bounded_maxima, column_extrema, run_moments

    maxima, minima = column_extrema(np.ascontiguousarray(s, dtype=np.float32))
    if maxima.size == 0:
        return _empty()
    tf = t.ravel()
    sf = s.ravel()
    # Bounding minima: the nearest minimum on each side within the same column (column
    # ends count as minima); the maximum must rise min_height above both.
    m, lo, hi = bounded_maxima(sf, maxima, minima, h, np.float32(min_height))
    if m.size == 0:
        return _empty()
    half = max(1, max_width // 2)
    lo = np.maximum(lo, m - half)
    hi = np.minimum(hi, m + half)
    if bias == "max-minimum":
        base = np.maximum(tf[lo], tf[hi])
    elif bias == "min-minimum":
        base = np.minimum(tf[lo], tf[hi])
    else:
        base = np.zeros(m.size, dtype=np.float32)
    # The raw maximum may sit one pixel off the smoothed one (``smooth``).
    peak = np.maximum(np.maximum(tf[m - 1], tf[m]), tf[m + 1])
    level = base + np.float32(bias_fraction) * (peak - base)
    # Moments over the contiguous run of pixels above the bias around the maximum, walking
    # outwards until the run ends: a neighbouring bump inside [lo, hi] is never counted.
    s0, s1, extent = run_moments(tf, m, level.astype(np.float32, copy=False), lo, hi, half)
    height = peak - level
    ok = s0 > 0
    # Mean slope of each flank above the bias (see min_slope).
    ok &= height >= min_slope * np.maximum(extent[0], 1)
    ok &= height >= min_slope * np.maximum(extent[1], 1)
    short = ok & (extent[0] + extent[1] + 1 < min_width)
    ok &= extent[0] + extent[1] + 1 >= min_width
    if narrow and np.any(short):
        # A line sharper than a pixel (sharp focus, a steep flank of the body) puts all but a
        # little of its light into one pixel: the bias fraction leaves that pixel alone and
        # its first moment would be the pixel centre. Above the bounding minima alone, the
        # two neighbours keep the light that spilt over, and the centroid of three pixels of
        # a pixel-integrated narrow line is its centre.
        k = np.flatnonzero(short)
        mk, b = m[k], base[k]
        below = np.maximum(tf[mk - 1] - b, 0.0)
        at = np.maximum(tf[mk] - b, 0.0)
        above = np.maximum(tf[np.minimum(mk + 1, tf.size - 1)] - b, 0.0)
        s0[k] = below + at + above
        s1[k] = above - below
        height[k] = peak[k] - b
        # a hot pixel spills nothing: the optics blur every line into its neighbours
        ok[k] = (s0[k] > 0) & (below + above > 0.0)
    # Trust: a peak is a line's crossing either way, but its first moment is biased or noisy
    # when it is dim (noise of a few DN moves it by a tenth of a pixel), when its bounding
    # minima differ (a neighbouring line or an edge overlaps one flank and the bias cuts it
    # unevenly), when one flank is much longer than the other, or when its top is clipped.
    trusted = ok.copy()
    crowded = np.zeros_like(ok)
    if trust:
        base_step = np.abs(tf[lo] - tf[hi]) / np.maximum(height, 1e-6)
        trusted &= height >= min_trust_height
        if clip_level is not None:
            # clipped: the top sits at the sensor's ceiling over more than one pixel
            at_top = (tf[m] >= clip_level) & (
                (tf[np.maximum(m - 1, 0)] >= clip_level) | (tf[m + 1] >= clip_level)
            )
            trusted &= ~at_top
        even = base_step <= max_base_step
        if bias != "none":
            # without a bias the run spans the whole window: its flanks say nothing
            flanks = np.abs(extent[0].astype(np.int32) - extent[1])
            even &= flanks <= max_flank_asymmetry
        crowded = trusted & ~even  # bright and unclipped: only a neighbour crowds it
        trusted &= even
    if flank_rule is not None and np.any(crowded):
        found = np.flatnonzero(trusted | crowded)
        col, row, area = _located(m[found], s0[found], s1[found], h)
        kept = flanked(col, row, area, trusted[found], crowded[found], flank_rule, h)
        trusted[found[kept]] = True
    dropped = int(np.count_nonzero(ok & ~trusted))
    col, row, area = _located(m[trusted], s0[trusted], s1[trusted], h)
    lo, hi = lo[trusted], hi[trusted]
    return PeakArrays(
        col=col,
        row=row,
        area=area,
        height=height[trusted].astype(np.float32),
        width=(hi - lo + 1).astype(np.int16),
        dropped=dropped,
    )


def _located(
    m: np.ndarray, s0: np.ndarray, s1: np.ndarray, h: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Column, first-moment row and area (float32, as stored) of the maxima at flat indices
    ``m`` of the transposed frame."""
    return (m // h).astype(np.int32), (m % h).astype(np.float64) + s1 / s0, s0.astype(np.float32)


class FirstMomentPeaks(Stage[Image, Peaks]):
    """Raster-line peaks per pixel column, located by the first moment of the intensities.

    The seed's peak detection: a peak is a rise then a fall of sufficient height and slope;
    its pixels run from the minimum left of the maximum to the minimum right of it; a bias is
    subtracted and the row is the intensity-weighted mean row, the area the intensity sum.

    Version 2: peaks whose location cannot be trusted (dim, bounding minima far apart, one
    flank much longer than the other, clipped top) are dropped and counted in the record's
    ``dropped``.
    Version 3: lines sharper than a pixel (one pixel above the bias) are kept, located by
    the centroid of three pixels above the bounding minima (``narrow``); bounding minima may
    differ by 0.4 of the height (was 0.3).
    Version 4: the heights are floors for a quiet camera, raised to ``noise_factor`` times
    the frame's own pixel noise (:mod:`~rasterserver_plugins.image_noise`): least height
    3 DN (was a fixed 5), least trusted height 3 DN (was 6), least flank slope 2 DN/px
    (was 2.5). The dim lines of dark scenes and light lines of a 1:2 code are found, and a
    noisy camera (3 DN rms) no longer fills the background with peaks.
    Version 5: a peak dropped only because a neighbouring line crowds it (unequal bounding
    minima or flanks; bright, not clipped) is kept where trusted peaks of the same line
    flank it in both adjacent columns and the line runs on beyond them
    (:mod:`~rasterserver_plugins.flanked_peaks`; ``flank_*``): the back's coverage gains a
    tenth of a point or more on the clinic scenes, at the line's own accuracy.
    Version 6: the extrema are found on the raw columns, as the seed finds them
    (``smooth`` False; ``noise_factor`` 5.7, was 3.5: the same heights over the raw
    column's noise). Where the back turns away from the camera, two lines two or three
    pixels apart are no longer one peak between them, and a dim narrow line is no longer
    flattened under the least height: on the raster with the closest lines the back's
    coverage gains about two tenths of a point (BENCHMARKS.md "Real bodies", 2026-12-01
    (42)-(43)).
    """

    name: ClassVar[str] = "peaks.first-moment"
    stage: ClassVar[str] = "peaks"
    version: ClassVar[str] = "6"
    input_type = Image
    output_type = Peaks

    class Params(StageParams):
        """Parameters of :class:`FirstMomentPeaks` (grey values in DN of the input)."""

        min_height: float = Field(
            3.0, ge=0, description="Least rise and fall of a peak (DN; see noise_factor)."
        )
        min_slope: float = Field(
            2.0, ge=0, description="Least mean slope of each flank above the bias (DN/px)."
        )
        bias: BiasMode = Field(
            "max-minimum", description="Base subtracted: larger/smaller bounding minimum or 0."
        )
        bias_fraction: float = Field(
            0.1, ge=0, lt=1, description="Fraction of the peak height added to the base."
        )
        min_width: int = Field(2, ge=1, description="Least contiguous pixels above the bias.")
        max_width: int = Field(
            25, ge=3, description="Largest window around a maximum (px, ~2.5 line spacings)."
        )
        smooth: bool = Field(
            False, description="Find extrema on [1, 2, 1]-smoothed columns (version 5)."
        )
        trust: bool = Field(True, description="Drop peaks whose location cannot be trusted.")
        min_trust_height: float = Field(
            3.0, ge=0, description="Least height above the bias of a trusted peak (DN)."
        )
        max_base_step: float = Field(
            0.4, ge=0, description="Largest difference of the bounding minima / height."
        )
        max_flank_asymmetry: int = Field(
            1, ge=0, description="Largest difference of the two flanks' lengths (px)."
        )
        clip_level: float | None = Field(
            None, description="Grey value at which the sensor clips (default: dtype maximum)."
        )
        narrow: bool = Field(
            True, description="Keep lines sharper than a pixel (3-pixel centroid)."
        )
        noise_factor: float = Field(
            5.7,
            ge=0,
            description="Heights at least this many times the frame's pixel noise (0: off).",
        )
        flank_tolerance: float = Field(
            0.4,
            ge=0,
            description="Keep a crowded peak within this of its flanking peaks' mean (px; 0: off).",
        )
        flank_span: float = Field(
            1.5, ge=0, description="Largest row difference of the two flanking peaks (px)."
        )
        flank_area_ratio: float = Field(
            1.5, ge=1, description="Largest ratio of the two flanking peaks' areas."
        )
        flank_run_on: float = Field(
            1.0,
            ge=0,
            description="The line runs on two columns out within this (px; 0: not asked).",
        )

    def run(self, data: Image, params: Params, context: StageContext) -> Peaks:
        """Detect the peaks of ``data.pixels``; an image without peaks gives empty arrays."""
        pixels = data.pixels
        found = detect_peaks(
            pixels,
            min_height=params.min_height,
            min_slope=params.min_slope,
            bias=params.bias,
            bias_fraction=params.bias_fraction,
            min_width=params.min_width,
            max_width=params.max_width,
            smooth=params.smooth,
            trust=params.trust,
            min_trust_height=params.min_trust_height,
            max_base_step=params.max_base_step,
            max_flank_asymmetry=params.max_flank_asymmetry,
            clip_level=params.clip_level,
            narrow=params.narrow,
            noise_factor=params.noise_factor,
            flank_rule=FlankRule(
                params.flank_tolerance,
                params.flank_span,
                params.flank_area_ratio,
                params.flank_run_on,
            ),
        )
        return found.to_record((int(pixels.shape[0]), int(pixels.shape[1])))
