"""Every command explains itself with --help; errors become a message and an exit code."""

from __future__ import annotations

import itertools
import os
import re
import subprocess
import sys

import click
import pytest
import typer.main

from rasterserver.cli import app, flowing, main

#: Terminal width the help is rendered at: wider than any source line, so every line break
#: the source's wrapping would leave in a paragraph shows as a short line.
_WIDTH = 200
#: Lines that begin a list item may follow a short line.
_LIST_ITEM = re.compile(r"\s*([-*\u2022]|\d+[.)])\s")


def _command_paths() -> list[list[str]]:
    root = typer.main.get_command(app)
    paths: list[list[str]] = []

    def walk(cmd: object, prefix: list[str]) -> None:
        paths.append(prefix)
        for name, sub in getattr(cmd, "commands", {}).items():
            walk(sub, [*prefix, name])

    walk(root, [])
    return paths


@pytest.mark.parametrize("path", _command_paths(), ids=lambda p: " ".join(p) or "root")
def test_every_command_has_help(path: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    assert main([*path, "--help"]) == 0
    out = capsys.readouterr().out
    assert "Usage" in out
    # A docstring or help text, not just the usage line.
    assert len(out.strip().splitlines()) > 3


def test_console_script_runs_and_reports_version() -> None:
    done = subprocess.run(
        [sys.executable, "-m", "rasterserver", "--version"],
        capture_output=True,
        text=True,
        check=False,
    )
    assert done.returncode == 0 and done.stdout.startswith("rasterserver ")


def test_unknown_command_is_a_usage_error(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["no-such-command"]) == 2
    assert "No such command" in capsys.readouterr().err


def ragged_breaks(help_text: str, width: int) -> list[str]:
    """The ragged line breaks in the description of a command's ``--help`` output.

    The description is what lies between the ``Usage:`` line and the first panel (a line
    starting with a box corner). Rich wraps a paragraph greedily at the terminal width, so
    within a paragraph (consecutive non-blank lines) a break is ragged when the next line's
    first word would have fitted on the line with two columns to spare: that break was in
    the text, not made by the terminal. A next line starting a list item is a meant break.

    Returns
    -------
    list of str
        ``"<line> / <next line>"`` for each ragged break; empty when the text flows.
    """
    lines = help_text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.strip().startswith("Usage:")) + 1
    panels = [i for i in range(start, len(lines)) if lines[i].lstrip().startswith("╭")]
    description = [line.rstrip() for line in lines[start : (panels or [len(lines)])[0]]]
    found = []
    for line, following in itertools.pairwise(description):
        if not line.strip() or not following.strip() or _LIST_ITEM.match(following):
            continue
        if len(line) + 1 + len(following.split()[0]) <= width - 2:
            found.append(f"{line.strip()!r} / {following.strip()!r}")
    return found


def test_ragged_breaks_finds_a_source_wrap() -> None:
    text = "\n Usage: x\n\n First line.\n\n A paragraph wrapped\n in the source.\n╭─ Options\n"
    assert ragged_breaks(text, _WIDTH) == ["'A paragraph wrapped' / 'in the source.'"]
    wrapped = "\n Usage: x\n\n " + "word " * 39 + "\n lastword\n"  # 196 wide: terminal's
    assert ragged_breaks(wrapped, _WIDTH) == []
    assert ragged_breaks("\n Usage: x\n\n A list:\n - one\n - two\n", _WIDTH) == []


def test_flowing_joins_paragraph_lines_and_keeps_lists() -> None:
    doc = """First line
    goes on.

    Second paragraph,
    wrapped.

    Items:
    - one
    - two
    """
    assert flowing(doc) == (
        "First line goes on.\n\nSecond paragraph, wrapped.\n\nItems:\n- one\n- two"
    )


@pytest.mark.parametrize("path", _command_paths(), ids=lambda p: " ".join(p) or "root")
def test_help_reads_as_flowing_paragraphs(
    path: list[str], capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Issue 11, defect 9: docstrings hard-wrapped in the source showed as ragged lines."""
    monkeypatch.setenv("COLUMNS", str(_WIDTH))
    assert main([*path, "--help"]) == 0
    out = capsys.readouterr().out
    assert max(len(line) for line in out.splitlines()) == _WIDTH  # rendered at that width
    assert ragged_breaks(out, _WIDTH) == []


def test_option_help_has_no_hard_line_breaks() -> None:
    """Option and argument help is one paragraph: a line break in it would show as is."""
    root = typer.main.get_command(app)
    found = []

    def walk(cmd: click.Command, name: str) -> None:
        for param in cmd.params:
            text = getattr(param, "help", None) or ""
            if "\n" in text:
                found.append(f"{name} {param.name}: {text!r}")
        for sub_name, sub in getattr(cmd, "commands", {}).items():
            walk(sub, f"{name} {sub_name}")

    walk(root, "rasterserver")
    assert found == []


def test_installed_command_help_flows() -> None:
    """The console script renders the same flowing help (here: a command with a docstring)."""
    done = subprocess.run(
        [sys.executable, "-m", "rasterserver", "process", "--help"],
        capture_output=True,
        text=True,
        check=False,
        env={**os.environ, "COLUMNS": str(_WIDTH)},
    )
    assert done.returncode == 0
    assert "Stored results of the same computation" in done.stdout
    assert ragged_breaks(done.stdout, _WIDTH) == []


@pytest.mark.parametrize(
    ("options", "code", "words"),
    [
        (["--database-url", "no-url"], 2, "the catalogue URL is not usable"),
        (["--database-url", "nosuchdialect://x"], 2, "the catalogue URL is not usable"),
        (["--database-url", "postgresql+psycopg://u:secret@127.0.0.1:1/x"], 8, "cannot use the"),
        (["--database-url", "sqlite:////proc/no/such/catalog.sqlite"], 8, "cannot use"),
    ],
)
def test_an_unusable_catalogue_is_a_message(
    options: list[str], code: int, words: str, tmp_path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["--archive", str(tmp_path / "a"), *options, "list"]) == code
    err = capsys.readouterr().err
    assert err.startswith(f"error: {words}") and err.count("\n") == 1
    assert "secret" not in err


def test_an_archive_folder_that_is_a_file_is_a_message(
    tmp_path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "a").write_text("not a folder")
    assert main(["--archive", str(tmp_path / "a"), "list"]) == 8
    assert capsys.readouterr().err.startswith(f"error: cannot use {tmp_path / 'a'}")


def test_a_bug_is_said_to_be_one_without_a_traceback(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    # the registry class itself: the plugins command imports it when it runs
    from rasterserver.registry import Registry

    def broken(*_args: object, **_kwargs: object) -> None:
        raise ZeroDivisionError("division by zero")

    monkeypatch.setattr(Registry, "discover", broken)
    assert main(["plugins"]) == 1
    err = capsys.readouterr().err
    assert "unexpected failure" in err and "ZeroDivisionError: division by zero" in err
    assert "Traceback" not in err and "--verbose" in err
