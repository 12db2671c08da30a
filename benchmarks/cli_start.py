"""Start-up time of the command line: ``--help``, ``list``, ``verify`` and ``plugins``.

Each command runs as a fresh process, as a user runs it, ``--runs`` times (default 15); the
commands take turns (round robin) so that a change in the machine's load during the run
falls on all of them alike. Reported per command: the median and the fastest wall-clock time,
and the median CPU time (user + system) of the child process, which depends less on what
else the machine is doing. ``python -c pass`` is the floor: the interpreter's own start.
The load average is recorded before and after, since the machine is shared.

Targets (issue 17): ``--help`` at most 0.3 s median, ``list`` at most 0.5 s median.

Run: ``.venv/bin/python benchmarks/cli_start.py [--runs 15] [--archive DIR] [--before DIR]``.
The demo archive (``rasterserver demo``, 3 visits) is made in benchmarks/out/cli-start-demo
when no ``--archive`` is given and it does not exist yet. ``--before DIR`` also times the CLI
of another source tree (an older commit unpacked with ``git archive COMMIT rasterserver | tar
-x -C DIR``; the installed plugins and migrations are shared), in the same round robin, so
that before and after are measured under the same load. Writes the "CLI start" section of
BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import datetime as dt
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _machine import machine, write_section

HERE = Path(__file__).resolve().parent
PYTHON = Path(sys.executable)
INSTALLED = PYTHON.with_name("rasterserver")
DEFAULT_ARCHIVE = HERE / "out" / "cli-start-demo"

HELP_TARGET_S = 0.3
LIST_TARGET_S = 0.5


def clean_env() -> dict[str, str]:
    """The environment without RASTERSERVER_* settings: only the options given decide."""
    return {k: v for k, v in os.environ.items() if not k.startswith("RASTERSERVER_")}


def make_demo(archive: Path) -> None:
    """Build the demo archive (3 simulated visits, processed) with the installed command."""
    print(f"making the demo archive in {archive} (a few minutes)", file=sys.stderr)
    subprocess.run(
        [str(INSTALLED), "--archive", str(archive), "demo", "--visits", "3"],
        check=True, env=clean_env(), stdout=subprocess.DEVNULL,
    )


def timed(argv: list[str]) -> tuple[float, float]:
    """Run ``argv`` once: (wall seconds, CPU seconds of the child). Fails on a non-zero exit."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    done = subprocess.run(argv, capture_output=True, env=clean_env(), check=False)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(argv)} exited {done.returncode}: {done.stderr.decode()}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu


def measure(commands: dict[str, list[str]], runs: int) -> dict[str, dict[str, float]]:
    """Median and fastest wall time and median CPU time of each command over ``runs`` runs."""
    walls: dict[str, list[float]] = {name: [] for name in commands}
    cpus: dict[str, list[float]] = {name: [] for name in commands}
    for argv in commands.values():  # one unmeasured run each: the file cache is warm
        timed(argv)
    for _ in range(runs):
        for name, argv in commands.items():
            wall, cpu = timed(argv)
            walls[name].append(wall)
            cpus[name].append(cpu)
    return {
        name: {
            "median": statistics.median(walls[name]),
            "min": min(walls[name]),
            "cpu": statistics.median(cpus[name]),
        }
        for name in commands
    }


def _before_note(before: str) -> str:
    if not before:
        return ""
    return (f" The rows marked *before* run the CLI of {before} (from its source tree, the "
            "interpreter started with `-c` instead of the console script) in the same round "
            "robin.")


#: What ``list`` cannot start without, step by step: each line imports what the one before
#: did and more (median CPU time of a fresh interpreter doing only that); the last lines are
#: what it no longer loads (issue 17), for comparison.
_TYPER = "import typer.main"
LIST_STEPS = {
    "Typer (no Pydantic: the plain options are coerced without its adapters)": _TYPER,
    "+ SQLAlchemy Core": f"{_TYPER}, sqlalchemy",
    "+ the catalogue's reader (Catalog, listing on Core views, schema check without Alembic)":
        f"{_TYPER}, rasterserver.catalog.catalog, rasterserver.catalog.listing",
    "no longer loaded: + the ORM and the catalogue's models":
        f"{_TYPER}, rasterserver.catalog.catalog, rasterserver.catalog.models",
    "no longer loaded: + Alembic (the old schema check)":
        f"{_TYPER}, rasterserver.catalog.catalog, rasterserver.catalog.migrate",
    "no longer loaded: + rasterserver.archive (NumPy, h5py)":
        f"{_TYPER}, rasterserver.archive",
    "no longer loaded: + Typer's Pydantic adapters (option coercion)":
        f"{_TYPER}, typer._adapters",
    "no longer loaded: + every command module (the lazy group imports the one run)":
        f"{_TYPER}, " + ", ".join(
            f"rasterserver.commands.{m}" for m in (
                "analyse", "calibrate", "compare", "db", "demo", "diff", "export", "ingest",
                "jobs", "listing", "patients", "plugins", "process", "prune", "reconstruct",
                "runs", "serve", "simulate", "stations", "tokens", "verify")),
}


def list_steps(runs: int) -> str:
    """A table of :data:`LIST_STEPS`: where the start of ``list`` goes."""
    rows = ["| imported | median CPU (s) |", "|---|---:|"]
    for label, code in LIST_STEPS.items():
        cpus = [timed([str(PYTHON), "-c", code])[1] for _ in range(runs)]
        rows.append(f"| {label} | {statistics.median(cpus):.3f} |")
    return "\n".join(rows)


def load() -> str:
    one, five, fifteen = os.getloadavg()
    return f"{one:.1f} / {five:.1f} / {fifteen:.1f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=15, help="runs per command (>= 10)")
    parser.add_argument("--archive", type=Path, default=None, help="archive to list")
    parser.add_argument("--before", type=Path, default=None,
                        help="also time the CLI of this source tree (e.g. an older commit)")
    parser.add_argument("--before-label", default=None,
                        help="what --before is, for the table (default: its path)")
    args = parser.parse_args()
    if args.runs < 10:
        parser.error("--runs must be at least 10: a median of fewer says little")
    archive = args.archive or DEFAULT_ARCHIVE
    if not archive.exists():
        if args.archive is not None:
            parser.error(f"--archive {archive}: no such folder")
        make_demo(archive)
    # a catalogue made by an older version is brought to the current schema first (list
    # refuses an old one); not timed
    subprocess.run([str(INSTALLED), "--archive", str(archive), "db", "upgrade"], check=True,
                   env=clean_env(), stdout=subprocess.DEVNULL)
    cli = [str(INSTALLED)]
    commands = {
        "python -c pass": [str(PYTHON), "-c", "pass"],
        "rasterserver --help": [*cli, "--help"],
        "rasterserver list": [*cli, "--archive", str(archive), "list"],
        "rasterserver verify": [*cli, "--archive", str(archive), "verify"],
        # discovers and imports every stage plugin, as process, stats and prune do
        "rasterserver plugins": [*cli, "plugins"],
    }
    before = ""
    if args.before is not None:
        source = args.before.resolve()
        before = args.before_label or str(source)
        # the older tree first on the path; plugins and migrations resolve as installed
        old = [str(PYTHON), "-c", f"import sys; sys.path.insert(0, {str(source)!r}); "
               "from rasterserver.cli import run; sys.argv[0] = 'rasterserver'; run()"]
        commands[f"before: rasterserver --help ({before})"] = [*old, "--help"]
        commands[f"before: rasterserver list ({before})"] = [
            *old, "--archive", str(archive), "list"]
        commands[f"before: rasterserver verify ({before})"] = [
            *old, "--archive", str(archive), "verify"]
    load_before = load()
    started = dt.datetime.now().astimezone()
    results = measure(commands, args.runs)
    steps = list_steps(args.runs)
    load_after = load()

    rows = [
        "| command | median wall (s) | fastest wall (s) | median CPU (s) |",
        "|---|---:|---:|---:|",
    ]
    for name, r in results.items():
        rows.append(f"| `{name}` | {r['median']:.3f} | {r['min']:.3f} | {r['cpu']:.3f} |")
    table = "\n".join(rows)
    print(f"{args.runs} runs each; load average (1/5/15 min) {load_before} before, "
          f"{load_after} after")
    print(table)
    print(steps)
    help_ok = results["rasterserver --help"]["median"] <= HELP_TARGET_S
    list_ok = results["rasterserver list"]["median"] <= LIST_TARGET_S
    print(f"--help {'meets' if help_ok else 'misses'} its target ({HELP_TARGET_S} s), "
          f"list {'meets' if list_ok else 'misses'} its target ({LIST_TARGET_S} s)")
    body = f"""
`benchmarks/cli_start.py`: the installed `rasterserver` console script, each command a fresh
process, {args.runs} runs each taken in turns; `list` and `verify` on the demo archive (3
visits, `rasterserver demo`). Wall time is what a user waits; CPU time (user + system of the
child) depends less on the load of the machine.{_before_note(before)}

Machine: {machine()}; run at {started:%Y-%m-%d %H:%M %Z}. **Load average (1/5/15 min)
{load_before} before and {load_after} after**: the machine was shared with other benchmark
and test runs, so wall times are longer than on an idle machine (compare with the floor).

{table}

Targets (issue 17): `--help` ≤ {HELP_TARGET_S} s median ({'met' if help_ok else 'missed'}),
`list` ≤ {LIST_TARGET_S} s median ({'met' if list_ok else 'missed'}). With the load above,
the waits are a matter of the machine's load as much as of the code: `list`'s median wall
time is {results["rasterserver list"]["median"] / results["rasterserver list"]["cpu"]:.1f}
times its CPU time, which is what it costs on an idle machine
({results["rasterserver list"]["cpu"]:.2f} s of CPU; before: see the *before* rows).
The root group is lazy (`rasterserver.cli.LazyGroup`): `--help` lists the commands from a
table of names and one-line help (`rasterserver.commands.COMMANDS`, checked against the
modules by a test) and imports no command module; a command imports its own module, and
Typer builds its options alone. Plain option values (strings, integers, flags, paths without
checks) are coerced without Typer's Pydantic adapters (`rasterserver.commands.light_params`,
checked against Typer's own coercion by a test), so `list` loads no Pydantic.

`plugins` imports every stage's module, as every command that discovers the stages does
(`process`, `stats`, `prune`); the stages import open3d and `scipy.signal` where they
compute (the mesh, the tangent angles), not when they are listed (tests/test_registry.py).

`--help`, `list` and `verify` load none of open3d, SciPy, Dask, matplotlib, FastAPI, uvicorn
and the simulator (tests/commands/test_cli_imports.py). `list` opens the catalogue alone (a
`Catalog`, no `Archive` and no file stores: no NumPy or h5py), reads it with SQLAlchemy Core
on light views of the three tables it queries (no ORM, no models), and checks the schema
revision by reading `alembic_version` and the migration files (no Alembic); the same test
checks that it loads none of these. Where its start goes now:

{steps}

Each step is the median of separate processes on a shared machine, so a step's share varies
by a few hundredths of a second from run to run. The rest is the CLI itself (the command
modules) and the query. What is left is SQLAlchemy Core's and Typer's own start.
"""
    write_section("CLI start", body)


if __name__ == "__main__":
    main()
