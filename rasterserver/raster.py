"""The raster diapositive: horizontal lines whose light/heavy pattern encodes their number.

Each line has a constant diapositive coordinate ``v`` (see :mod:`rasterserver.optics`), a
width and a kind, ``"light"`` (narrow) or ``"heavy"`` (wide, 40:60 as in the seed). Reading
the kinds of ``window`` consecutive lines anywhere on the back identifies their absolute
position: the kind sequence is a *window code* (a de Bruijn-like sequence). The default code
(90 lines) has window 9 and minimum Hamming distance 2 between any two windows, so a single
misread line in a window never produces another valid window — it is detected, not
mis-numbered. Runs of equal kinds are at most 4 long. Why 9 and not 7: a window-7
m-sequence (127 lines) identifies positions with 7 lines but any two windows may differ in
one place only; with distance 2 a randomised search finds ~60 lines for window 8 and 90
for window 9.

The definition is data (JSON, format ``rasterserver.raster/1``, see ``docs/formats.md``).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Any, Literal

import numpy as np

from rasterserver.json_document import JsonDocument

#: ``format`` tag of the raster definition JSON.
RASTER_FORMAT = "rasterserver.raster/1"

LineKind = Literal["light", "heavy"]
KINDS: tuple[LineKind, LineKind] = ("light", "heavy")


@dataclass(frozen=True, eq=False)
class Raster(JsonDocument):
    """A raster diapositive definition.

    Attributes
    ----------
    name : str
        Identifier (``"default"``).
    numbers : numpy.ndarray
        ``(L,)`` int absolute line numbers, in the order of increasing ``v``.
    positions : numpy.ndarray
        ``(L,)`` float line centres ``v`` in diapositive units, strictly increasing
        (top of the back to bottom).
    kinds : tuple of str
        ``(L,)`` ``"light"`` or ``"heavy"``.
    widths : numpy.ndarray
        ``(L,)`` float line widths in diapositive units (full width of the transparent
        stripe, before projector defocus).
    window : int
        Code window length: any ``window`` consecutive kinds identify the position.
    min_distance : int
        Minimum Hamming distance between any two code windows (1: unique only; 2: a single
        misread kind is detectable).
    description : str
        Free text.
    """

    name: str
    numbers: np.ndarray
    positions: np.ndarray
    kinds: tuple[str, ...]
    widths: np.ndarray
    window: int
    min_distance: int = 1
    description: str = ""

    def __post_init__(self) -> None:
        numbers = np.asarray(self.numbers, dtype=np.int64).ravel()
        positions = np.asarray(self.positions, dtype=np.float64).ravel()
        widths = np.asarray(self.widths, dtype=np.float64).ravel()
        kinds = tuple(str(k) for k in self.kinds)
        n = numbers.size
        if not (positions.size == widths.size == len(kinds) == n):
            raise ValueError("numbers, positions, kinds and widths must have the same length")
        if n > 1 and np.any(np.diff(positions) <= 0):
            raise ValueError("line positions must be strictly increasing")
        if bad := sorted(set(kinds) - set(KINDS)):
            raise ValueError(f"unknown line kinds {bad}; expected 'light' or 'heavy'")
        if np.any(widths <= 0):
            raise ValueError("line widths must be positive")
        object.__setattr__(self, "numbers", numbers)
        object.__setattr__(self, "positions", positions)
        object.__setattr__(self, "widths", widths)
        object.__setattr__(self, "kinds", kinds)

    @property
    def n_lines(self) -> int:
        """Number of lines."""
        return int(self.numbers.size)

    @property
    def code(self) -> np.ndarray:
        """``(L,)`` uint8 code bits: 0 light, 1 heavy."""
        return np.array([k == "heavy" for k in self.kinds], dtype=np.uint8)

    @property
    def spacing(self) -> float:
        """Median distance between neighbouring lines (diapositive units)."""
        return float(np.median(np.diff(self.positions))) if self.n_lines > 1 else 0.0

    def index_of(self, number: int) -> int:
        """Index of the line with absolute ``number``."""
        hits = np.flatnonzero(self.numbers == number)
        if hits.size == 0:
            raise KeyError(f"no line number {number} in raster {self.name!r}")
        return int(hits[0])

    def window_positions(
        self, kinds: list[str] | np.ndarray, *, max_mismatches: int = 0
    ) -> np.ndarray:
        """Indices where an observed run of consecutive kinds fits the code.

        See :func:`window_code_position`.
        """
        return window_code_position(self, kinds, max_mismatches=max_mismatches)

    # ---------------------------------------------------------------- serialisation
    def to_dict(self) -> dict[str, Any]:
        """JSON-ready definition (format ``rasterserver.raster/1``)."""
        return {
            "format": RASTER_FORMAT,
            "name": self.name,
            "description": self.description,
            "units": "diapositive units (v coordinate of the projector model)",
            "code": {"window": int(self.window), "min_distance": int(self.min_distance)},
            "lines": [
                {"number": int(n), "v": float(p), "kind": k, "width": float(w)}
                for n, p, k, w in zip(
                    self.numbers, self.positions, self.kinds, self.widths, strict=True
                )
            ],
        }



def _kinds_to_bits(kinds: list[str] | np.ndarray) -> np.ndarray:
    arr = np.asarray(kinds)
    if arr.dtype.kind in "US":
        if bad := sorted(set(arr.tolist()) - set(KINDS)):
            raise ValueError(f"unknown line kinds {bad}")
        return (arr == "heavy").astype(np.uint8)
    return arr.astype(np.uint8)


def window_code_position(
    raster: Raster, kinds: list[str] | np.ndarray, *, max_mismatches: int = 0
) -> np.ndarray:
    """Where in the raster a run of consecutive observed line kinds fits.

    Parameters
    ----------
    raster : Raster
        The diapositive definition.
    kinds : sequence of str or array of 0/1
        Kinds of consecutive lines, top to bottom (``"light"``/``"heavy"`` or bits with
        1 = heavy). Any length up to the number of lines.
    max_mismatches : int
        Number of kinds allowed to differ (0: exact match).

    Returns
    -------
    numpy.ndarray
        Indices (into ``raster.numbers``) of the first line of every matching placement,
        ascending. With an exact run of ``raster.window`` kinds there is at most one.
    """
    bits = _kinds_to_bits(kinds)
    code = raster.code
    k = bits.size
    if k == 0 or k > code.size:
        return np.zeros(0, dtype=np.int64)
    windows = np.lib.stride_tricks.sliding_window_view(code, k)
    mismatches = np.count_nonzero(windows != bits[None, :], axis=1)
    return np.flatnonzero(mismatches <= max_mismatches).astype(np.int64)


def code_min_distance(code: np.ndarray, window: int) -> int:
    """Minimum Hamming distance between any two length-``window`` windows of ``code``."""
    return closest_windows(code, window)[0]


def closest_windows(code: np.ndarray, window: int) -> tuple[int, int, int]:
    """The two length-``window`` windows of ``code`` that differ in the fewest places.

    Windows of up to 63 bits are packed into integers and compared by XOR and bit count, a
    block of rows at a time, so a raster of thousands of lines needs a few megabytes (the
    full boolean comparison needs lines² x window bytes).

    Parameters
    ----------
    code : numpy.ndarray
        ``(L,)`` bits (1 = heavy).
    window : int
        Window length, ``1 <= window <= L``.

    Returns
    -------
    (int, int, int)
        The distance and the indices ``i < j`` of the first lines of the two windows;
        ``(window, 0, 0)`` when there are fewer than two windows.
    """
    bits = np.asarray(code, dtype=np.uint8).ravel()
    windows = np.lib.stride_tricks.sliding_window_view(bits, window)
    n = windows.shape[0]
    if n < 2:
        return window, 0, 0
    packed = None
    if window <= 63:
        weights = np.left_shift(np.uint64(1), np.arange(window, dtype=np.uint64))
        packed = (windows.astype(np.uint64) * weights).sum(axis=1, dtype=np.uint64)
    best = (window + 1, 0, 0)
    block = max(1, 2_000_000 // (n * (1 if packed is not None else window)))
    for start in range(0, n - 1, block):
        rows = np.arange(start, min(start + block, n - 1))
        if packed is not None:
            d = np.bitwise_count(packed[rows, None] ^ packed[None, :]).astype(np.int64)
        else:
            d = np.count_nonzero(windows[rows, None, :] != windows[None, :, :], axis=2)
        d[np.arange(n)[None, :] <= rows[:, None]] = window + 1  # each pair once, i < j
        flat = int(np.argmin(d))
        i, j = divmod(flat, n)
        if d[i, j] < best[0]:
            best = (int(d[i, j]), int(rows[i]), int(j))
    return best


@lru_cache(maxsize=32)
def _search_code(
    n: int, window: int, min_distance: int, max_run: int, seed: int
) -> tuple[int, ...]:
    if min_distance not in (1, 2):
        raise ValueError("min_distance must be 1 or 2")
    rng = np.random.default_rng(seed)
    n_words = 1 << window
    mask = n_words - 1
    # blocked[w] > 0: w is used or within distance < min_distance of a used window
    blocked = np.zeros(n_words, dtype=np.int32)
    flips = [0] if min_distance == 1 else [0, *[1 << b for b in range(window)]]

    def mark(word: int, delta: int) -> None:
        for f in flips:
            blocked[word ^ f] += delta

    def run_ok(seq: list[int]) -> bool:
        return len(seq) <= max_run or len(set(seq[-max_run - 1 :])) > 1

    budget = [500_000]

    def extend(seq: list[int], word: int) -> bool:
        if len(seq) == n:
            return True
        for bit in (int(b) for b in rng.permutation(2)):
            budget[0] -= 1
            if budget[0] < 0:
                return False
            cand = ((word << 1) & mask) | bit
            seq.append(bit)
            if blocked[cand] == 0 and run_ok(seq):
                mark(cand, +1)
                if extend(seq, cand):
                    return True
                mark(cand, -1)
            seq.pop()
        return False

    for first in (int(w) for w in rng.permutation(n_words)):
        seq = [(first >> (window - 1 - i)) & 1 for i in range(window)]
        if not run_ok(seq):
            continue
        mark(first, +1)
        if extend(seq, first):
            break
        mark(first, -1)
        if budget[0] < 0:
            break
    else:
        seq = []
    if len(seq) != n:
        raise RuntimeError(f"no {n}-line code with window {window} found; relax constraints")
    return tuple(seq)


def generate_window_code(
    n_lines: int, *, window: int = 8, min_distance: int = 2, max_run: int = 4, seed: int = 0
) -> np.ndarray:
    """A binary sequence whose length-``window`` windows are all distinct.

    Randomised depth-first search (deterministic for a given ``seed``). With
    ``min_distance=2`` any two windows differ in at least two places, so a single misread
    bit is detected; at most ``2**(window-1)`` windows exist then, so
    ``n_lines <= 2**(window-1) + window - 1``.

    Parameters
    ----------
    n_lines : int
        Sequence length.
    window : int
        Window length.
    min_distance : int
        1 or 2.
    max_run : int
        Longest run of equal bits allowed (keeps light and heavy lines mixed locally).
    seed : int
        Search seed.

    Returns
    -------
    numpy.ndarray
        ``(n_lines,)`` uint8 bits, 1 = heavy.
    """
    return np.array(_search_code(n_lines, window, min_distance, max_run, seed), dtype=np.uint8)


#: The default 90-line code (1 = heavy), ``generate_window_code(90, window=9, seed=0)``;
#: stored so that importing the module does not repeat the search.
DEFAULT_CODE = (
    "111010000110100100011000111101110010010100111100010101000100110110011101101010111010110110"
)


def make_raster(
    n_lines: int = 90,
    *,
    spacing: float = 10.0,
    centre: float = 499.5,
    light_width: float = 0.9,
    heavy_width: float = 1.35,
    window: int = 9,
    min_distance: int = 2,
    first_number: int = 1,
    seed: int = 0,
    code: np.ndarray | str | None = None,
    name: str = "default",
) -> Raster:
    """Equally spaced coded raster centred on diapositive coordinate ``centre``.

    Parameters
    ----------
    n_lines : int
        Number of lines (90 covers the default field of view with margin).
    spacing : float
        Line spacing in diapositive units (10 → 1 line per cm on the back).
    centre : float
        ``v`` of the middle of the raster (the default station maps the world origin to
        ``v = 499.5``).
    light_width, heavy_width : float
        Line widths (units), 40:60 as in the seed.
    window, min_distance, seed : int
        Code parameters, see :func:`generate_window_code`.
    code : numpy.ndarray or str, optional
        Use these bits (1 = heavy) instead of searching.
    first_number : int
        Absolute number of the top line.
    name : str
        Raster name.

    Returns
    -------
    Raster
    """
    if code is None:
        bits = generate_window_code(n_lines, window=window, min_distance=min_distance, seed=seed)
    else:
        bits = np.array([int(c) for c in code], dtype=np.uint8)
        if bits.size != n_lines:
            raise ValueError(f"code has {bits.size} bits for {n_lines} lines")
    positions = centre + (np.arange(n_lines) - (n_lines - 1) / 2.0) * spacing
    kinds = tuple(KINDS[b] for b in bits)
    widths = np.where(bits == 1, heavy_width, light_width)
    return Raster(
        name=name,
        numbers=np.arange(first_number, first_number + n_lines),
        positions=positions,
        kinds=kinds,
        widths=widths,
        window=window,
        min_distance=code_min_distance(bits, window),
        description=(
            f"{n_lines} horizontal lines, {spacing:g} units apart, light {light_width:g} / heavy "
            f"{heavy_width:g} units wide; window-{window} code, minimum window distance "
            f"{code_min_distance(bits, window)}"
        ),
    )


@lru_cache(maxsize=1)
def default_raster() -> Raster:
    """The default diapositive: 90 lines, 1 per cm on the back, window 9, distance 2."""
    return make_raster(code=DEFAULT_CODE)


def m_sequence(window: int = 7, *, taps: tuple[int, ...] | None = None) -> np.ndarray:
    """A maximal-length sequence: every non-zero ``window``-bit word once per period.

    The output of a Fibonacci linear-feedback shift register with a primitive feedback
    polynomial, started from all ones; ``2**window - 1`` bits. Read as a raster code it has
    window ``window`` but minimum window distance 1 (two windows may differ in one line):
    a single misread line can place a window elsewhere, which the numbering must survive.

    Parameters
    ----------
    window : int
        Register length, 3-10 (primitive taps are tabulated for these).
    taps : tuple of int, optional
        Feedback taps (1-based bit positions) instead of the tabulated ones.

    Returns
    -------
    numpy.ndarray
        ``(2**window - 1,)`` uint8 bits.
    """
    table = {
        3: (3, 2),
        4: (4, 3),
        5: (5, 3),
        6: (6, 5),
        7: (7, 6),
        8: (8, 6, 5, 4),
        9: (9, 5),
        10: (10, 7),
    }
    if taps is None:
        if window not in table:
            raise ValueError(f"no tabulated primitive polynomial for window {window} (3-10)")
        taps = table[window]
    state = [1] * window
    out = []
    for _ in range((1 << window) - 1):
        out.append(state[-1])
        fb = 0
        for t in taps:
            fb ^= state[t - 1]
        state = [fb, *state[:-1]]
    return np.array(out, dtype=np.uint8)


#: ``generate_window_code(110, window=8, min_distance=1, seed=3)`` (stored, as the default).
W8_CODE = (
    "01111011101101110011000011101111010010101100010010011001010000101110001011001110101000101010"
    "010000110011010111"
)
#: ``generate_window_code(96, window=9, min_distance=2, seed=6)``.
W9_CODE = (
    "111000010111100011110100001100111011001101110011000100100101001111001011"
    "101011011010101000101010"
)


@lru_cache(maxsize=1)
def mseq7_raster() -> Raster:
    """Clinic raster: a window-7 maximal-length sequence, 127 lines 7.8 units apart, 40:60.

    Two code windows may differ in one line only (minimum distance 1).
    """
    return make_raster(
        127,
        spacing=7.8,
        light_width=0.72,
        heavy_width=1.08,
        code=m_sequence(7),
        window=7,
        name="mseq7",
    )


@lru_cache(maxsize=1)
def w8_thin_raster() -> Raster:
    """Clinic raster: 110 lines 9 units apart, window 8, distance 1, light:heavy 1:2."""
    return make_raster(
        110,
        spacing=9.0,
        light_width=0.6,
        heavy_width=1.2,
        code=W8_CODE,
        window=8,
        name="w8-1to2",
    )


@lru_cache(maxsize=1)
def w9_faint_raster() -> Raster:
    """Clinic raster: 96 lines 10 units apart, window 9, distance 2, light:heavy 45:55
    (heavy lines only 22 % brighter: the kinds are hard to tell apart)."""
    return make_raster(
        96,
        spacing=10.0,
        light_width=0.9,
        heavy_width=1.1,
        code=W9_CODE,
        window=9,
        name="w9-45to55",
    )


@lru_cache(maxsize=1)
def mseq8_raster() -> Raster:
    """Held-out clinic raster: the first 136 lines of a window-8 maximal-length sequence,
    7.2 units apart, light:heavy 35:65 (heavy lines 1.86 times as wide).

    Two code windows may differ in one line only (minimum distance 1). Never used while the
    numbering was tuned: the real-body benchmark sees scenes through it only on request
    (``benchmarks/real_bodies.py --raster mseq8-35to65``), to measure the numbering on a
    code, line count, spacing and ratio it was not fitted to.
    """
    return make_raster(
        136,
        spacing=7.2,
        light_width=0.7,
        heavy_width=1.3,
        code=m_sequence(8)[:136],
        window=8,
        name="mseq8-35to65",
    )


@lru_cache(maxsize=1)
def mseq8_twin_raster() -> Raster:
    """Tuning twin of the held-out raster: the first 132 lines of another window-8
    maximal-length sequence (taps 8, 6, 5, 3), 7.4 units apart, light:heavy 35:65.

    The held-out raster's kind (window 8, minimum distance 1, heavy lines nearly twice as
    wide, dense lines) with another code, line count and spacing: the numbering may be tuned
    on scenes seen through it (``benchmarks/real_bodies.py --raster mseq8b-35to65``) without
    looking at the held-out raster itself.
    """
    return make_raster(
        132,
        spacing=7.4,
        light_width=0.7,
        heavy_width=1.3,
        code=m_sequence(8, taps=(8, 6, 5, 3))[:132],
        window=8,
        name="mseq8b-35to65",
    )


_BUILTIN = {
    "default": default_raster,
    "mseq7": mseq7_raster,
    "w8-1to2": w8_thin_raster,
    "w9-45to55": w9_faint_raster,
    "mseq8-35to65": mseq8_raster,
    "mseq8b-35to65": mseq8_twin_raster,
}

#: Built-in clinic rasters (other codes, line counts and light:heavy ratios than the
#: default one), used by the real-body benchmark.
CLINIC_RASTERS: tuple[str, ...] = ("mseq7", "w8-1to2", "w9-45to55")
#: Built-in rasters held out from the numbering's tuning (measured on, never looked at).
HELD_OUT_RASTERS: tuple[str, ...] = ("mseq8-35to65",)
#: Built-in rasters for tuning only, each the twin of a held-out one (its kind, not its code).
TUNING_RASTERS: tuple[str, ...] = ("mseq8b-35to65",)


def get_raster(name: str) -> Raster:
    """A built-in raster definition by name (``"default"``, ``"mseq7"``, ``"w8-1to2"``,
    ``"w9-45to55"``, ``"mseq8-35to65"``, ``"mseq8b-35to65"``)."""
    try:
        return _BUILTIN[name]()
    except KeyError:
        raise KeyError(f"unknown built-in raster {name!r}; known: {sorted(_BUILTIN)}") from None
