"""Records of the image-processing stages: peaks, lines, ordered lines, numbered lines.

Each record extends the previous one with the result of one more stage, so every record
carries the per-peak arrays of :class:`Peaks` unchanged (same length, same order: sorted by
column, then row) and a consumer of a later record never has to join tables::

    Peaks           col, row, area, height, width, image_shape
    Lines           + line_id
    OrderedLines    + order, line_order, line_component
    NumberedLines   + number, line_number, kind_observed, confidence, reason

Per-peak arrays have one entry per detected peak; per-line arrays (``line_*``,
``kind_observed``) are indexed by ``line_id`` (``0 .. n_lines - 1``).

A stage builds its record from the previous one with :meth:`Peaks.extend`, which carries
every field of the earlier record forward, so a field added to :class:`Peaks` (as
``dropped`` was) reaches the later records without touching the stages::

    Lines.extend(peaks, line_id=line_id)
"""

from __future__ import annotations

import dataclasses
from typing import Any, ClassVar, Self

import numpy as np

from rasterserver.errors import InputError
from rasterserver.records import Record

__all__ = ["Lines", "NumberedLines", "OrderedLines", "Peaks"]


def _check_1d(record: Record, names: tuple[str, ...], n: int, kinds: str) -> None:
    for name in names:
        value = getattr(record, name)
        if value.ndim != 1 or value.shape[0] != n:
            raise InputError(
                f"{type(record).__name__}.{name} must have shape ({n},), got {value.shape}"
            )
        if value.dtype.kind not in kinds:
            raise InputError(
                f"{type(record).__name__}.{name} must be numeric ({kinds}), got {value.dtype}"
            )


class Peaks(Record):
    """Raster-line intensity peaks found in the pixel columns of one frame.

    Attributes
    ----------
    col : numpy.ndarray
        ``(N,)`` int32 pixel column of each peak.
    row : numpy.ndarray
        ``(N,)`` float64 sub-pixel row (pixel-centre convention: the top pixel's centre is
        row 0), the first moment of the bias-subtracted intensities.
    area : numpy.ndarray
        ``(N,)`` float32 sum of the bias-subtracted intensities (DN x px): the line's
        intensity, which tells light from heavy lines.
    height : numpy.ndarray
        ``(N,)`` float32 maximum bias-subtracted intensity (DN).
    width : numpy.ndarray
        ``(N,)`` int16 pixels from the minimum left of the maximum to the minimum right of it,
        both included (clipped to the detector's window).
    image_shape : numpy.ndarray
        ``(2,)`` int64 ``(rows, columns)`` of the frame.
    dropped : int, optional
        Peaks the detector found but dropped because their location cannot be trusted
        (dim, clipped, asymmetric); None when the detector does not judge trust. Keyword
        only, carried along by the later line records.

    Notes
    -----
    Peaks are sorted by ``(col, row)``.
    """

    kind: ClassVar[str] = "peaks"
    col: np.ndarray
    row: np.ndarray
    area: np.ndarray
    height: np.ndarray
    width: np.ndarray
    image_shape: np.ndarray
    # keyword only and None by default: the subclasses' fields need no default, and a
    # record without it keeps its content hash
    dropped: int | None = dataclasses.field(default=None, kw_only=True)

    @classmethod
    def extend(cls, earlier: Peaks, **new: Any) -> Self:
        """This record built from an ``earlier`` stage's record and the ``new`` fields.

        Parameters
        ----------
        earlier : Peaks
            A record of an earlier stage (or of this one): every field it has is carried
            forward unchanged unless given in ``new``.
        **new
            The fields this record adds (or replaces).

        Returns
        -------
        Self
            The new record (validated).

        Raises
        ------
        TypeError
            When ``earlier`` is not a :class:`Peaks` record or a field is missing.
        """
        if not isinstance(earlier, Peaks):
            raise TypeError(
                f"{cls.__name__}.extend needs a Peaks record, not {type(earlier).__name__}"
            )
        carried = {
            f.name: getattr(earlier, f.name)
            for f in dataclasses.fields(earlier)
            if f.init and f.name not in new
        }
        own = {f.name for f in dataclasses.fields(cls) if f.init}
        return cls(**{k: v for k, v in carried.items() if k in own}, **new)

    @property
    def n_peaks(self) -> int:
        """Number of peaks."""
        return int(self.col.shape[0])

    def validate(self) -> None:
        """Check shapes, dtypes and the ``(col, row)`` order."""
        if self.image_shape.shape != (2,) or self.image_shape.dtype.kind not in "iu":
            raise InputError(f"image_shape must be 2 integers, got {self.image_shape!r}")
        if self.col.ndim != 1:
            raise InputError(f"col must be 1-D, got shape {self.col.shape}")
        n = self.col.shape[0]
        _check_1d(self, ("col",), n, "iu")
        _check_1d(self, ("row", "area", "height"), n, "f")
        _check_1d(self, ("width",), n, "iuf")
        if n > 1:
            dc = np.diff(self.col.astype(np.int64))
            if np.any(dc < 0) or np.any((dc == 0) & (np.diff(self.row) < 0)):
                raise InputError("peaks must be sorted by (col, row)")


class Lines(Peaks):
    """Peaks joined into raster lines across neighbouring columns (line search).

    Attributes
    ----------
    line_id : numpy.ndarray
        ``(N,)`` int32 line of each peak, ``0 .. n_lines - 1``; -1 for peaks in no line.
        A line has at most one peak per column.
    """

    kind: ClassVar[str] = "lines"
    line_id: np.ndarray

    @property
    def n_lines(self) -> int:
        """Number of lines (``max(line_id) + 1``)."""
        return int(self.line_id.max()) + 1 if self.line_id.size else 0

    def validate(self) -> None:
        """Check the per-peak line ids."""
        super().validate()
        _check_1d(self, ("line_id",), self.n_peaks, "iu")
        if self.line_id.size and self.line_id.min() < -1:
            raise InputError("line_id must be >= -1")


class OrderedLines(Lines):
    """Lines arranged in their topological (top-to-bottom) order (line sequence analysis).

    Lines that cannot be linked to each other fall into separate *components*; the order is
    relative within a component (each component starts at 0, counting downwards).

    Attributes
    ----------
    order : numpy.ndarray
        ``(N,)`` int32 relative line index of each peak's line within its component;
        -1 when the peak's line is unordered (or the peak is in no line).
    line_order : numpy.ndarray
        ``(n_lines,)`` int32 the same per line.
    line_component : numpy.ndarray
        ``(n_lines,)`` int32 component of each line, -1 when unordered.
    """

    kind: ClassVar[str] = "ordered-lines"
    order: np.ndarray
    line_order: np.ndarray
    line_component: np.ndarray

    def validate(self) -> None:
        """Check per-peak and per-line arrays against each other."""
        super().validate()
        _check_1d(self, ("order",), self.n_peaks, "iu")
        n_lines = self.line_order.shape[0]
        _check_1d(self, ("line_order", "line_component"), n_lines, "iu")
        if self.n_lines > n_lines:
            raise InputError(f"{self.n_lines} lines but per-line tables of {n_lines}")


class NumberedLines(OrderedLines):
    """Ordered lines with their absolute raster line numbers (line numbering).

    Attributes
    ----------
    number : numpy.ndarray
        ``(N,)`` int32 absolute raster line number of each peak; -1 when unnumbered.
    line_number : numpy.ndarray
        ``(n_lines,)`` int32 the same per line.
    kind_observed : numpy.ndarray
        ``(n_lines,)`` int8 observed kind of each line: 0 light, 1 heavy, -1 unknown.
    confidence : float
        Confidence of the numbering in [0, 1]: the smallest margin (in log-likelihood per
        line, squashed) between the best and the second-best code offset over the numbered
        components; 0 when nothing is numbered.
    reason : str
        Why lines were left unnumbered; empty when every ordered line is numbered.
    """

    kind: ClassVar[str] = "numbered-lines"
    number: np.ndarray
    line_number: np.ndarray
    kind_observed: np.ndarray
    confidence: float
    reason: str

    def validate(self) -> None:
        """Check the numbering arrays."""
        super().validate()
        _check_1d(self, ("number",), self.n_peaks, "iu")
        _check_1d(self, ("line_number", "kind_observed"), self.line_order.shape[0], "iu")
        if not 0.0 <= self.confidence <= 1.0:
            raise InputError(f"confidence must lie in [0, 1], got {self.confidence}")
