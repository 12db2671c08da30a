"""Which detected hole is which: the seven points matched to the seven-point layout by the
affine map that fits best over all 5040 orderings; the marker breaks every symmetry of the
grid, so exactly one ordering fits. A plate with a missing, extra or unidentifiable hole is
refused."""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from rasterserver.errors import InputError

PERMUTATIONS = np.array(list(itertools.permutations(range(7))), dtype=np.int64)


def identify_holes(
    points: np.ndarray, layout: np.ndarray, *, tolerance: float = 0.03
) -> tuple[np.ndarray, float]:
    """Order seven image points as the layout's holes by the best affine fit.

    Parameters
    ----------
    points : numpy.ndarray
        ``(7, 2)`` image points in any order.
    layout : numpy.ndarray
        ``(7, 2)`` hole layout in plate coordinates.
    tolerance : float
        Largest accepted rms misfit as a fraction of the pattern's rms radius in the image (a
        plate seen obliquely departs from an affine image by a few per mille).

    Returns
    -------
    order : numpy.ndarray
        ``(7,)``: ``points[order[j]]`` is hole ``j``.
    rms : float
        Rms misfit (px).

    Raises
    ------
    InputError
        When no ordering fits, or two fit equally well.
    """
    design = np.column_stack([layout, np.ones(7)])
    pinv = np.linalg.pinv(design)
    candidates = points[PERMUTATIONS]  # (5040, 7, 2)
    maps = np.einsum("ij,pjk->pik", pinv, candidates)  # (5040, 3, 2)
    misfit = np.einsum("ij,pjk->pik", design, maps) - candidates
    rms = np.sqrt((misfit**2).sum(axis=2).mean(axis=1))
    linear = maps[:, :2, :]
    det = linear[:, 0, 0] * linear[:, 1, 1] - linear[:, 0, 1] * linear[:, 1, 0]
    # the camera sees the plate's front: a mirrored match is not a view of the plate
    rms = np.where(det > 0, rms, np.inf)
    best = int(np.argmin(rms))
    # the pattern's size in the image: its rms radius times the map's scale
    radius = np.sqrt(((layout - layout.mean(axis=0)) ** 2).sum(axis=1).mean())
    spacing = max(float(np.sqrt(abs(det[best])) * radius), 1e-9)
    ranked = np.sort(rms)
    if not ranked[0] <= tolerance * spacing:
        raise InputError(
            f"the holes do not form the control-point pattern (best fit off by "
            f"{ranked[0]:.1f} px rms): a hole mis-detected, or a foreign dark spot"
        )
    if ranked[1] <= 2.0 * tolerance * spacing:
        raise InputError("the hole pattern is ambiguous: two orderings of the holes fit")
    return PERMUTATIONS[best], float(ranked[0])


def layout_self_map(layout: np.ndarray, *, tolerance: float = 0.06) -> np.ndarray | None:
    """An ordering of the layout other than the identity that an affine map fits, if any.

    A layout with such a self-map (a symmetric pattern: a regular grid, a circle of holes)
    cannot identify its points in an image; :func:`load_control_points` refuses it. Mirror
    images count too unless the plates are seen from the front only: they are, so only maps
    with a positive determinant are tried (as :func:`identify_holes` does).

    Returns
    -------
    numpy.ndarray or None
        ``(7,)`` the other ordering, or ``None`` when only the identity fits.
    """
    layout = np.asarray(layout, dtype=np.float64)
    design = np.column_stack([layout, np.ones(7)])
    pinv = np.linalg.pinv(design)
    candidates = layout[PERMUTATIONS]
    maps = np.einsum("ij,pjk->pik", pinv, candidates)
    misfit = np.einsum("ij,pjk->pik", design, maps) - candidates
    rms = np.sqrt((misfit**2).sum(axis=2).mean(axis=1))
    linear = maps[:, :2, :]
    det = linear[:, 0, 0] * linear[:, 1, 1] - linear[:, 0, 1] * linear[:, 1, 0]
    radius = np.sqrt(((layout - layout.mean(axis=0)) ** 2).sum(axis=1).mean())
    # the image's scale is sqrt|det| times the layout's: compare misfits in the image's terms
    scaled = rms / np.maximum(np.sqrt(np.abs(det)), 1e-9)
    fits = (det > 0.05) & (scaled <= tolerance * radius)
    fits[0] = False  # permutation 0 is the identity
    hits = np.flatnonzero(fits)
    return None if hits.size == 0 else PERMUTATIONS[hits[np.argmin(scaled[hits])]]


def _bases(layout: np.ndarray) -> list[tuple[int, int, int]]:
    """Two disjoint, well-conditioned layout triples: any one missing hole spares one."""
    triples = list(itertools.combinations(range(7), 3))

    def area(t: tuple[int, int, int]) -> float:
        a, b, c = layout[list(t)]
        (x1, y1), (x2, y2) = b - a, c - a
        return abs(float(x1 * y2 - x2 * y1))

    first = max(triples, key=area)
    second = max((t for t in triples if not set(t) & set(first)), key=area)
    return [first, second]


@dataclass(frozen=True)
class LayoutMatch:
    """Blobs that an affine image of the layout puts at its holes (-1: no blob there)."""

    blobs: tuple[int, ...]
    rms: float

    @property
    def found(self) -> int:
        return sum(b >= 0 for b in self.blobs)


def find_patterns(
    centres: np.ndarray, layout: np.ndarray, *, tolerance: float, max_anisotropy: float
) -> list[LayoutMatch]:
    """Every placement of the layout on the blobs with at least five holes in place.

    Hypotheses: an ordered pair of blobs as two points of a layout triple gives a similarity;
    the blobs near the similarity's third point (loosely, for oblique views) complete an
    affine map; the map predicts all seven holes, each taken by the nearest blob within
    ``tolerance`` times the pattern's rms radius in the image. Vectorised over hypotheses.
    """
    n = len(centres)
    if n < 3:
        return []
    tree = cKDTree(centres)
    radius_mm = float(np.sqrt(((layout - layout.mean(axis=0)) ** 2).sum(axis=1).mean()))
    zc = centres[:, 0] + 1j * centres[:, 1]
    zl = layout[:, 0] + 1j * layout[:, 1]
    i, j = np.nonzero(~np.eye(n, dtype=bool))
    found: dict[tuple[int, ...], LayoutMatch] = {}
    for a, b, c in _bases(layout):
        scale = (zc[j] - zc[i]) / (zl[b] - zl[a])
        guess = zc[i] + scale * (zl[c] - zl[a])
        loose = 0.5 * np.abs(scale) * abs(zl[c] - zl[a])
        near = tree.query_ball_point(np.column_stack([guess.real, guess.imag]), r=loose)
        lengths = np.fromiter((len(x) for x in near), np.int64, len(near))
        if lengths.sum() == 0:
            continue
        ii, jj = np.repeat(i, lengths), np.repeat(j, lengths)
        kk = np.concatenate([np.asarray(x, np.int64) for x in near if x])
        ok = (kk != ii) & (kk != jj)
        ii, jj, kk = ii[ok], jj[ok], kk[ok]
        if ii.size == 0:
            continue
        src = np.array([[*layout[a], 1.0], [*layout[b], 1.0], [*layout[c], 1.0]])
        inv = np.linalg.inv(src)  # affine A (3 x 2): src @ A = the three image points
        dst = np.stack([centres[ii], centres[jj], centres[kk]], axis=1)  # (T, 3, 2)
        maps = np.einsum("ij,tjk->tik", inv, dst)
        lin = maps[:, :2, :]
        det = lin[:, 0, 0] * lin[:, 1, 1] - lin[:, 0, 1] * lin[:, 1, 0]
        sv = np.linalg.svd(lin, compute_uv=False)
        keep = (det > 0) & (sv[:, 1] > 0) & (sv[:, 0] <= max_anisotropy * sv[:, 1])
        maps, sv = maps[keep], sv[keep]
        if maps.shape[0] == 0:
            continue
        predicted = np.einsum("ij,tjk->tik", np.column_stack([layout, np.ones(7)]), maps)
        dist, idx = tree.query(predicted.reshape(-1, 2))
        dist, idx = np.asarray(dist).reshape(-1, 7), np.asarray(idx).reshape(-1, 7)
        tol = np.maximum(tolerance * np.sqrt(sv[:, 0] * sv[:, 1]) * radius_mm, 1.5)
        hit = dist <= tol[:, None]
        enough = hit.sum(axis=1) >= 5
        for row in np.flatnonzero(enough):
            blobs = tuple(int(x) if h else -1 for x, h in zip(idx[row], hit[row], strict=True))
            taken = [x for x in blobs if x >= 0]
            if len(set(taken)) != len(taken):
                continue  # two holes on one blob: not a placement
            if blobs not in found:
                found[blobs] = LayoutMatch(blobs, float(np.sqrt(np.mean(dist[row][hit[row]] ** 2))))
    return list(found.values())
