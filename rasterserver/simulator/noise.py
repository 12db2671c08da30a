"""The camera sensor: photo-electrons → digital numbers, with shot and read noise.

Model (per pixel): ``n ~ Poisson(e)`` photo-electrons for an expected signal ``e``; the well
clips at ``full_well``; the read-out adds Gaussian noise of ``read_noise`` electrons rms;
``DN = round(gain * n + offset)`` clipped to ``[0, 2**bit_depth - 1]``. So, away from
saturation, ``mean(DN) = gain * e + offset`` and
``var(DN) = gain**2 * (e + read_noise**2) + 1/12`` (the last term from rounding).
"""

from __future__ import annotations

import numpy as np


def expose(
    electrons: np.ndarray,
    *,
    rng: np.random.Generator,
    gain: float,
    offset: float,
    read_noise: float,
    full_well: float,
    bit_depth: int,
    shot_noise: bool = True,
    noise: bool = True,
) -> np.ndarray:
    """Digitise an expected photo-electron image.

    Parameters
    ----------
    electrons : numpy.ndarray
        ``(H, W)`` expected photo-electrons per pixel (noise-free).
    rng : numpy.random.Generator
        Source of all randomness (shot noise drawn first, then read noise).
    gain : float
        Digital numbers per electron.
    offset : float
        Black level in DN.
    read_noise : float
        Read-out noise, electrons rms.
    full_well : float
        Well capacity in electrons (saturation).
    bit_depth : int
        8, 10, 12 or 16: output ``uint8`` for 8 bits, ``uint16`` otherwise.
    shot_noise : bool
        Draw Poisson photo-electrons (else use the expected value).
    noise : bool
        False: no noise at all (deterministic rounding only).

    Returns
    -------
    numpy.ndarray
        ``(H, W)`` uint8 or uint16 image.
    """
    if bit_depth not in (8, 10, 12, 14, 16):
        raise ValueError(f"unsupported bit depth {bit_depth}")
    e = np.asarray(electrons, dtype=np.float64)
    e = np.maximum(e, 0.0)
    if noise and shot_noise:
        e = rng.poisson(e).astype(np.float64)
    e = np.minimum(e, full_well)
    if noise and read_noise > 0:
        e = e + rng.normal(0.0, read_noise, size=e.shape)
    dn = np.rint(gain * e + offset)
    top = (1 << bit_depth) - 1
    dtype = np.uint8 if bit_depth == 8 else np.uint16
    return np.clip(dn, 0, top).astype(dtype)


def expected_statistics(
    electrons: float | np.ndarray, *, gain: float, offset: float, read_noise: float
) -> tuple[np.ndarray, np.ndarray]:
    """Mean and variance (DN) of :func:`expose` away from saturation and clipping.

    Returns
    -------
    mean, variance : numpy.ndarray
        ``gain * e + offset`` and ``gain**2 * (e + read_noise**2) + 1/12``.
    """
    e = np.asarray(electrons, dtype=np.float64)
    return gain * e + offset, gain**2 * (e + read_noise**2) + 1.0 / 12.0
