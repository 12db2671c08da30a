"""Benchmark the raw store's compression settings on synthetic rasterstereography frames.

Writes the same frames with each compression setting through :class:`RawStore` (hashing,
HDF5 write, fsync, publish: everything the ingest pays), reads them back with hash
verification, and prints a markdown table of bytes per frame, write and read speed.

Usage::

    .venv/bin/python benchmarks/store_compression.py [--frames 240] [--dir /archive/disk]
        [--append BENCHMARKS.md]

``--dir`` should be on the filesystem the archive will use: fsync cost depends on it.
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import sys
import tempfile
import time
import uuid
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from rasterserver.store import FrameToWrite, RawStore

SETTINGS = ("none", "lzf", "gzip-1", "gzip-4", "shuffle+gzip-1", "shuffle+lzf")
SEED = 20261122
GAIN_E_PER_DN = 20.0
READ_NOISE_DN = 0.8


def synthetic_frame(
    rng: np.random.Generator, rows: int = 604, cols: int = 576, *, bits: int = 8
) -> np.ndarray:
    """One camera frame: ~60 bright bent horizontal lines on a dim gradient, with noise.

    Parameters
    ----------
    rng : numpy.random.Generator
        Source of the per-frame shift and noise.
    rows, cols : int
        Frame size (portrait camera: more rows than columns).
    bits : int
        8 for a ``uint8`` frame; 10 to 16 for a ``uint16`` frame with that many used bits.

    Returns
    -------
    numpy.ndarray
        ``uint8`` or ``uint16`` frame.
    """
    full_scale = float(2**bits - 1)
    y = np.arange(rows, dtype=np.float64)[:, None]
    x = np.arange(cols, dtype=np.float64)[None, :]
    # Dim background brighter towards the bottom and the middle, like a lit back.
    background = full_scale * (0.06 + 0.10 * y / rows) * (1.0 - 0.3 * ((x / cols - 0.5) * 2) ** 2)
    n_lines = 60
    spacing = rows / (n_lines + 1)
    # The back's curvature bends each projected line; a small shift changes every frame.
    bend = 0.8 * spacing * np.sin(np.pi * x / cols) + rng.uniform(-2, 2)
    sigma = 1.3  # ~3 px full width at half maximum
    lines = np.zeros((rows, cols))
    for k in range(1, n_lines + 1):
        centre = k * spacing + bend
        lines += np.exp(-0.5 * ((y - centre) / sigma) ** 2)
    signal = background + 0.7 * full_scale * lines
    # Shot noise of a sensor with GAIN electrons per 8-bit grey level, plus read noise:
    # about 3 grey levels RMS on the lines and 1 on the background, as on a machine-vision
    # camera at moderate gain.
    gain = GAIN_E_PER_DN * 255.0 / full_scale
    electrons = rng.poisson(np.clip(signal, 0, None) * gain).astype(np.float64)
    noisy = electrons / gain + rng.normal(0.0, READ_NOISE_DN * full_scale / 255.0, signal.shape)
    dtype = np.uint8 if bits == 8 else np.uint16
    return np.clip(np.rint(noisy), 0, full_scale).astype(dtype)


@dataclass(frozen=True)
class Result:
    """Measurements of one compression setting."""

    setting: str
    bytes_per_frame: float
    ratio: float
    write_fps: float
    write_mbps: float
    read_fps: float
    read_mbps: float


def measure(
    setting: str, frames: list[np.ndarray], per_file: int, workdir: Path, repeat: int = 1
) -> Result:
    """Write ``frames`` in files of ``per_file`` frames with ``setting``, then read them back.

    With ``repeat`` > 1 the fastest run counts: on a shared machine the slower runs measure
    the other tenants, not the store.
    """
    runs = [_run_once(setting, frames, per_file, workdir) for _ in range(max(1, repeat))]
    stored_bytes = runs[0][0]
    write_s = min(run[1] for run in runs)
    read_s = min(run[2] for run in runs)
    raw_bytes = sum(frame.nbytes for frame in frames)
    n = len(frames)
    return Result(
        setting=setting,
        bytes_per_frame=stored_bytes / n,
        ratio=raw_bytes / stored_bytes,
        write_fps=n / write_s,
        write_mbps=raw_bytes / write_s / 1e6,
        read_fps=n / read_s,
        read_mbps=raw_bytes / read_s / 1e6,
    )


def _run_once(
    setting: str, frames: list[np.ndarray], per_file: int, workdir: Path
) -> tuple[int, float, float]:
    """Return stored bytes, write seconds and read seconds of one pass."""
    root = Path(tempfile.mkdtemp(prefix=f"bench-{setting.replace('+', '_')}-", dir=workdir))
    try:
        store = RawStore(root, compression=setting)
        uids: list[str] = []
        start = time.perf_counter()
        for first in range(0, len(frames), per_file):
            uid = uuid.uuid4().hex
            batch = [
                FrameToWrite(i - first, "raster", frames[i])
                for i in range(first, min(first + per_file, len(frames)))
            ]
            store.write(uid, batch)
            uids.append(uid)
        write_s = time.perf_counter() - start
        stored_bytes = sum(store.path_for(uid).stat().st_size for uid in uids)
        start = time.perf_counter()
        for uid in uids:
            store.read_all(uid, verify=True)
        read_s = time.perf_counter() - start
    finally:
        shutil.rmtree(root, ignore_errors=True)
    return stored_bytes, write_s, read_s


def table(title: str, results: list[Result], frame_bytes: int) -> str:
    """Render results as a markdown table."""
    lines = [
        f"{title} (uncompressed {frame_bytes} bytes per frame)",
        "",
        "| compression | bytes/frame | ratio | write frames/s | write MB/s "
        "| read frames/s | read MB/s |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in results:
        lines.append(
            f"| `{r.setting}` | {r.bytes_per_frame:,.0f} | {r.ratio:.2f} | {r.write_fps:,.0f} "
            f"| {r.write_mbps:,.0f} | {r.read_fps:,.0f} | {r.read_mbps:,.0f} |"
        )
    return "\n".join(lines)


def machine() -> str:
    """Describe the machine: CPU count and model, Python and library versions."""
    model = "unknown CPU"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    import h5py

    return (
        f"{os.cpu_count()} CPUs ({model}), Python {platform.python_version()}, "
        f"numpy {np.__version__}, h5py {h5py.__version__} (HDF5 {h5py.version.hdf5_version}), "
        f"{platform.system()} {platform.release()}"
    )


def append_atomically(path: Path, text: str) -> None:
    """Append ``text`` to ``path`` in one ``write`` (O_APPEND), creating it with a heading."""
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
    except FileExistsError:
        pass
    else:
        with os.fdopen(fd, "w") as fresh:
            fresh.write("# Benchmarks\n")
    fd = os.open(path, os.O_WRONLY | os.O_APPEND)
    try:
        os.write(fd, text.encode())
    finally:
        os.close(fd)


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark; print (and optionally append) the markdown report."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=240, help="604x576 uint8 frames")
    parser.add_argument("--large-frames", type=int, default=24,
                        help="2448x2048 uint16 (12-bit) frames; 0 to skip")
    parser.add_argument("--per-file", type=int, default=12, help="frames per acquisition file")
    parser.add_argument("--repeat", type=int, default=3, help="runs per setting; fastest counts")
    parser.add_argument("--settings", nargs="*", default=list(SETTINGS))
    parser.add_argument("--dir", type=Path, default=None, help="where to write (default: tmp)")
    parser.add_argument("--append", type=Path, default=None, help="append report to this file")
    args = parser.parse_args(argv)

    load_before = os.getloadavg()[0]
    rng = np.random.default_rng(SEED)
    workdir = args.dir or Path(tempfile.gettempdir())
    workdir.mkdir(parents=True, exist_ok=True)
    sections = []
    scenarios = [("604x576 uint8", args.frames, 604, 576, 8)]
    if args.large_frames:
        scenarios.append(("2448x2048 uint16 (12-bit)", args.large_frames, 2448, 2048, 12))
    for title, count, rows, cols, bits in scenarios:
        frames = [synthetic_frame(rng, rows, cols, bits=bits) for _ in range(count)]
        # One warm-up file so imports and HDF5 initialisation are not measured.
        measure(args.settings[0], frames[: args.per_file], args.per_file, workdir)
        results = [
            measure(s, frames, args.per_file, workdir, args.repeat) for s in args.settings
        ]
        sections.append(table(f"**{title}**, {count} frames, {args.per_file} per file, "
                              f"best of {args.repeat}",
                              results, frames[0].nbytes))
    report = (
        f"Measured {datetime.now(UTC):%Y-%m-%d %H:%M} UTC on {machine()}; "
        f"written to `{workdir}` (fsync included); load average before the run "
        f"{load_before:.1f}.\n\n" + "\n\n".join(sections) + "\n"
    )
    print(report)
    if args.append is not None:
        append_atomically(args.append, "\n## Raw store compression\n\n" + report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
