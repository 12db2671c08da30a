"""``rasterserver plugins`` lists real entry-point plugins, broken ones with their reason."""

from __future__ import annotations

import json
import sys
import textwrap
from collections.abc import Iterator
from pathlib import Path

import pytest

from rasterserver.cli import main
from rasterserver.registry import STAGE_GROUP

PLUGIN_MODULE = '''
"""A third-party stage package."""

from __future__ import annotations

import numpy as np

from rasterserver.records import Image
from rasterserver.stage import Stage, StageContext, StageParams


class InvertImage(Stage[Image, Image]):
    """Invert grey values."""

    name = "thirdparty.invert"
    stage = "invert"
    version = "1.0"
    input_type = Image
    output_type = Image

    def run(self, data: Image, params: StageParams, context: StageContext) -> Image:
        return Image(np.iinfo(data.pixels.dtype).max - data.pixels, role=data.role)


def not_a_stage() -> None:
    """A function where a Stage should be."""
'''

MODULES = ("cli_thirdparty_plugin", "cli_thirdparty_broken")


@pytest.fixture
def installed(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """Install ``thirdparty-plugin 1.0`` with one good and two broken entry points."""
    (tmp_path / "cli_thirdparty_plugin.py").write_text(textwrap.dedent(PLUGIN_MODULE))
    (tmp_path / "cli_thirdparty_broken.py").write_text('raise ImportError("needs libfoo")\n')
    info = tmp_path / "thirdparty_plugin-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: thirdparty-plugin\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text(
        f"[{STAGE_GROUP}]\n"
        "thirdparty.invert = cli_thirdparty_plugin:InvertImage\n"
        "thirdparty.needs-libfoo = cli_thirdparty_broken:Stage\n"
        "thirdparty.function = cli_thirdparty_plugin:not_a_stage\n"
    )
    for module in MODULES:
        sys.modules.pop(module, None)
    monkeypatch.syspath_prepend(str(tmp_path))
    yield tmp_path
    for module in MODULES:
        sys.modules.pop(module, None)


def _lines_of(out: str, name: str) -> list[str]:
    lines = out.splitlines()
    index = next(i for i, line in enumerate(lines) if line.startswith(name + " "))
    following = lines[index + 1] if index + 1 < len(lines) else ""
    return [lines[index], following]


def test_lists_third_party_and_broken_plugins(
    installed: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["plugins"]) == 0
    out = capsys.readouterr().out
    assert out.splitlines()[0].split() == [
        "NAME",
        "STAGE",
        "VERSION",
        "INPUT",
        "OUTPUT",
        "PACKAGE",
        "STATUS",
    ]
    row, _ = _lines_of(out, "thirdparty.invert")
    expected = "thirdparty.invert invert 1.0 image image thirdparty-plugin 1.0 ok"
    assert row.split() == expected.split()
    row, reason = _lines_of(out, "thirdparty.needs-libfoo")
    assert row.split()[-3:] == ["thirdparty-plugin", "1.0", "broken"]
    assert reason.strip() == "reason: import failed: ImportError: needs libfoo"
    row, reason = _lines_of(out, "thirdparty.function")
    assert row.split()[-1] == "broken"
    assert "cli_thirdparty_plugin:not_a_stage is 'function', not a" in reason


def test_json_output(installed: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["plugins", "--json"]) == 0
    entries = {entry["name"]: entry for entry in json.loads(capsys.readouterr().out)}
    assert entries["thirdparty.invert"] == {
        "name": "thirdparty.invert",
        "entry_point": "cli_thirdparty_plugin:InvertImage",
        "status": "ok",
        "stage": "invert",
        "version": "1.0",
        "input_kind": "image",
        "output_kind": "image",
        "package": "thirdparty-plugin",
        "package_version": "1.0",
        "summary": "Invert grey values.",
        "error": None,
    }
    broken = entries["thirdparty.needs-libfoo"]
    assert broken["status"] == "broken"
    assert broken["stage"] is None
    assert broken["error"] == "import failed: ImportError: needs libfoo"


def test_filter_by_stage_kind(installed: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["plugins", "--stage", "invert", "--json"]) == 0
    captured = capsys.readouterr()
    assert [entry["name"] for entry in json.loads(captured.out)] == ["thirdparty.invert"]
    # The broken ones may be of that kind too: hidden, but not silently.
    assert "2 broken plugin(s) of unknown stage kind not shown" in captured.err
    assert "thirdparty.needs-libfoo" in captured.err

    assert main(["plugins", "--stage", "no-such-kind"]) == 0
    out = capsys.readouterr().out
    assert "no stage plugins of kind 'no-such-kind'" in out
    assert "invert" in out  # the installed kinds are suggested


def test_cli_keeps_working_with_broken_plugins(
    installed: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["--version"]) == 0
    assert main(["plugins", "--help"]) == 0
    out = capsys.readouterr().out
    assert STAGE_GROUP in out
    assert "broken" in out


def test_help_explains_the_listing(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["plugins", "--help"]) == 0
    out = " ".join(capsys.readouterr().out.split())
    assert "List every installed stage plugin" in out
    assert "--json" in out and "--stage" in out
    assert "still exits with 0" in out


def test_without_third_party_plugins_the_command_succeeds(
    capsys: pytest.CaptureFixture[str],
) -> None:
    # Whatever is installed (the built-ins, or nothing yet), the listing works and none of
    # the fixture plugins of other tests leak in.
    assert main(["plugins", "--json"]) == 0
    names = [entry["name"] for entry in json.loads(capsys.readouterr().out)]
    assert "thirdparty.invert" not in names
