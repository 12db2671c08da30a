"""The simulator's six control-point frames, rendered once per test process.

Supersampling 2 (not the CLI's default 3) keeps the rendering to a few seconds; the hole
centres and line peaks it gives are as accurate as the calibration needs (the figures tested
are met with margin). Default noise, fixed seeds.
"""

from __future__ import annotations

import atexit
import shutil
import tempfile
from functools import cache
from pathlib import Path

from rasterserver.cli import main


@cache
def rendered_dir() -> Path:
    """A folder written by ``rasterserver simulate calibration-body --supersample 2``."""
    out = Path(tempfile.mkdtemp(prefix="rs-calibration-frames-"))
    atexit.register(shutil.rmtree, out, ignore_errors=True)
    code = main(["simulate", "calibration-body", "--supersample", "2", "--seed", "0",
                 "--out", str(out)])
    if code != 0:
        raise RuntimeError(f"simulate calibration-body failed with exit code {code}")
    return out
