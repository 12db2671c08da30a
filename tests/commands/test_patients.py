"""``rasterserver patient`` in a subprocess: the identifier rules, on both catalogues."""

from __future__ import annotations

import subprocess

from installed_cli import run_installed

from rasterserver.config import Settings


def run(settings: Settings, *args: str) -> subprocess.CompletedProcess[str]:
    """Run the installed ``rasterserver`` on the test archive and catalogue."""
    return run_installed(
        *args, archive=settings.archive, database_url=settings.database_url, timeout=120
    )


def test_identifiers_are_checked_and_look_alikes_refused(settings: Settings) -> None:
    assert run(settings, "db", "upgrade").returncode == 0
    added = run(settings, "patient", "add", "e\u0301-P1")  # decomposed é
    assert added.returncode == 0 and added.stdout == "patient \u00e9-P1 registered\n"
    for identifier, code, message in (
        ("\u00c9-p1", 4, "exists already"),  # composed, other case: the same patient
        ("SL/01", 2, "must not contain '/'"),
        ("a\nb", 2, "printable characters only"),
        (" P-2", 2, "begin or end with a space"),
    ):
        done = run(settings, "patient", "add", identifier)
        assert done.returncode == code, (identifier, done.stderr)
        assert message in done.stderr and "Traceback" not in done.stderr
    listed = run(settings, "patient", "list").stdout.splitlines()
    assert [line.split("\t")[0] for line in listed] == ["\u00e9-P1"]
