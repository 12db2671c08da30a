"""The private directory of the metrics files of ``rasterserver serve --workers N``.

With several workers, ``prometheus_client`` keeps each worker's counts in memory-mapped files
of a directory shared by the workers (:mod:`rasterserver.api.metrics`). ``serve`` makes a fresh
one in the temporary directory at start and removes it at exit; a server that is killed
(``kill -9``, the OOM killer, a power cut) cannot remove it. So each start also removes the
directories of servers that are gone: the directory names its server in an ``owner`` file
(:func:`rasterserver.runner.current_runner`: host, pid and process start time, so a pid the
kernel has given to another process since does not keep it), and a directory is removed only
when that server is certainly gone (:func:`rasterserver.runner.runner_gone`). Directories made
before the ``owner`` file existed are judged by the workers' pids in their file names.

The temporary directory rather than the archive: the files are written on every request
through memory maps, which want a local (often in-memory) file system, and they are worth
nothing once the server has stopped.

This module does not import ``prometheus_client``: the variable naming the directory must be
set before that is imported.
"""

from __future__ import annotations

import re
import shutil
import tempfile
import time
from pathlib import Path

from rasterserver.runner import current_runner, local_host, runner_gone

__all__ = ["PREFIX", "make_metrics_dir", "remove_stale_metrics_dirs"]

#: Name prefix of the directories in the temporary directory.
PREFIX = "rasterserver-metrics-"
OWNER = "owner"
# prometheus_client's files: <kind>_<pid>.db (counter_123.db, gauge_livesum_123.db, ...)
_PID_FILE = re.compile(r"_(\d+)\.db$")
# A directory without owner and without files may be one that a server of an older version
# has just made: left alone for this long.
_EMPTY_GRACE_S = 3600.0


def _gone(directory: Path) -> bool:
    """Whether ``directory`` belongs to a server that is certainly gone."""
    try:
        return runner_gone((directory / OWNER).read_text().strip())
    except FileNotFoundError:
        pass
    except OSError:
        return False
    # made before the owner file: gone when none of its workers is alive
    pids = [int(m.group(1)) for f in directory.iterdir() if (m := _PID_FILE.search(f.name))]
    if not pids:
        return time.time() - directory.stat().st_mtime > _EMPTY_GRACE_S
    host = local_host()
    return all(runner_gone(f"{host}:{pid}") for pid in pids)


def remove_stale_metrics_dirs(root: Path | None = None) -> list[Path]:
    """Remove the metrics directories of servers that are gone; return them.

    Parameters
    ----------
    root : Path, optional
        Where to look; the temporary directory by default.

    Returns
    -------
    list of Path
        The directories removed.
    """
    root = Path(root or tempfile.gettempdir())
    removed = []
    for directory in sorted(root.glob(PREFIX + "*")):
        try:
            if not directory.is_dir() or directory.is_symlink() or not _gone(directory):
                continue
        except OSError:  # another user's, or removed meanwhile
            continue
        shutil.rmtree(directory, ignore_errors=True)
        if not directory.exists():
            removed.append(directory)
    return removed


def make_metrics_dir(root: Path | None = None) -> Path:
    """Remove stale metrics directories, then make this server's and name it its owner.

    Parameters
    ----------
    root : Path, optional
        Where to make it; the temporary directory by default.

    Returns
    -------
    Path
        The new, empty (but for its ``owner`` file) directory, private to this user.
    """
    remove_stale_metrics_dirs(root)
    directory = Path(tempfile.mkdtemp(prefix=PREFIX, dir=root))
    (directory / OWNER).write_text(current_runner() + "\n")
    return directory
