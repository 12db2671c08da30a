"""The compiled loops run where numba can write no cache (read-only package and home)."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np

from rasterserver.compiled import kernel


def test_a_kernel_computes() -> None:
    @kernel(error_model="numpy")
    def halves(x: np.ndarray) -> np.ndarray:
        return x / 0.0

    with np.errstate(divide="ignore", invalid="ignore"):
        want = np.array([1.0, 0.0]) / 0.0
    np.testing.assert_array_equal(halves(np.array([1.0, 0.0])), want)  # inf, nan as numpy


def test_kernels_without_a_writable_cache_still_run() -> None:
    # Only numba's zip-file locator: it finds no place for a module on disk, as when neither
    # the package folder nor the home folder can be written. njit(cache=True) then raises
    # "cannot cache function ...: no locator available" at import; the kernels must compile
    # in the process instead.
    code = (
        "import numpy as np\n"
        "from rasterserver_plugins.peak_scan import column_extrema\n"
        "s = np.array([[0, 1, 5, 1, 0]], np.float32)\n"
        "print(column_extrema(s)[0].tolist())\n"
    )
    env = {**os.environ, "NUMBA_CACHE_LOCATOR_CLASSES": "ZipCacheLocator"}
    env.pop("NUMBA_CACHE_DIR", None)
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300
    )
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "[2]"
