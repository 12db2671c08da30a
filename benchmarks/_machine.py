"""Machine description and BENCHMARKS.md section writing shared by the benchmark scripts."""

from __future__ import annotations

import argparse
import datetime as dt
import os
import platform
import re
from pathlib import Path

BENCHMARKS_MD = Path(__file__).resolve().parent.parent / "BENCHMARKS.md"


def machine() -> str:
    """One line naming the machine: CPU model, cores, memory, Python, date."""
    cpu = "unknown CPU"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem = ""
    try:
        kb = int(re.search(r"MemTotal:\s+(\d+)", Path("/proc/meminfo").read_text())[1])
        mem = f", {kb / 1024**2:.0f} GiB"
    except (OSError, TypeError):
        pass
    return (
        f"{cpu}, {os.cpu_count()} cores{mem}, {platform.system()} {platform.release()}, "
        f"Python {platform.python_version()}; measured {dt.date.today().isoformat()}"
    )


def write_section(title: str, body: str) -> None:
    """Replace (or append) the ``## title`` section of BENCHMARKS.md with ``body``."""
    text = BENCHMARKS_MD.read_text() if BENCHMARKS_MD.exists() else "# Benchmarks\n"
    section = f"## {title}\n\n{body.strip()}\n"
    pattern = re.compile(rf"^## {re.escape(title)}\n.*?(?=^## |\Z)", re.S | re.M)
    if pattern.search(text):
        text = pattern.sub(lambda _m: section + "\n", text, count=1)
    else:
        text = text.rstrip() + "\n\n" + section
    BENCHMARKS_MD.write_text(text.rstrip() + "\n")


def write_subsection(title: str, heading: str, body: str) -> None:
    """Write ``### heading`` as the newest subsection of the ``## title`` section.

    A section that keeps a dated history (newest first) must not lose it when a run writes
    its figures: a subsection of the same heading is replaced, otherwise the new one goes
    first, above the older ones; the section is appended when BENCHMARKS.md lacks it.
    """
    text = BENCHMARKS_MD.read_text() if BENCHMARKS_MD.exists() else "# Benchmarks\n"
    sub = f"### {heading}\n\n{body.strip()}\n\n"
    match = re.search(rf"^## {re.escape(title)}\n.*?(?=^## |\Z)", text, re.S | re.M)
    if match is None:
        text = text.rstrip() + f"\n\n## {title}\n\n" + sub
    else:
        section = match.group(0)
        same = re.compile(rf"^### {re.escape(heading)}\n.*?(?=^### |\Z)", re.S | re.M)
        if same.search(section):
            section = same.sub(lambda _m: sub, section, count=1)
        else:
            first = re.search(r"^### ", section, re.M)
            at = first.start() if first else len(section)
            section = section[:at].rstrip() + "\n\n" + sub + section[at:]
        text = text[: match.start()] + section.rstrip() + "\n\n" + text[match.end() :]
    BENCHMARKS_MD.write_text(text.rstrip() + "\n")


def subsection_heading(heading: str | None, script: str) -> str:
    """``heading`` when given, else today's date and the script that measured."""
    return heading or f"{dt.date.today().isoformat()}: `benchmarks/{Path(script).name}`"


def add_write_options(parser: argparse.ArgumentParser) -> None:
    """``--write`` and ``--heading``, the options of the scripts that keep a dated history
    in their BENCHMARKS.md section (:func:`write_subsection`, :func:`subsection_heading`)."""
    parser.add_argument(
        "--write",
        action="store_true",
        help="write the figures as the newest dated subsection of their BENCHMARKS.md section"
        " (older subsections are kept)",
    )
    parser.add_argument(
        "--heading",
        default=None,
        help="the subsection's heading (default: today's date and the script's name)",
    )
