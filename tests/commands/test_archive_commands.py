"""The archive commands end to end through the CLI, on SQLite and PostgreSQL."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest

from rasterserver.cli import main
from rasterserver.config import Settings


def test_ingest_list_verify(cli, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    frame = np.random.default_rng(1).integers(0, 256, (604, 576), dtype=np.uint8)
    cv2.imwrite(str(tmp_path / "f.png"), frame)
    assert cli("patient", "add", "P7", "--name", "A B", "--sex", "male") == 0
    assert (
        cli(
            "ingest",
            str(tmp_path / "f.png"),
            "--patient",
            "P7",
            "--acquired-at",
            "2025-02-03T10:00Z",
        )
        == 0
    )
    uid = capsys.readouterr().out.split()[-4].rstrip(":")
    assert cli("list", "--json", "--patient", "P7") == 0
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [r["uid"] for r in rows] == [uid]
    assert rows[0]["frames"][0]["shape"] == [604, 576]
    assert cli("verify") == 0
    assert "OK" in capsys.readouterr().out


def test_bad_input_exit_codes(cli, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "x.png").write_text("no image")
    cli("patient", "add", "P7")
    capsys.readouterr()
    assert cli("ingest", str(tmp_path / "x.png"), "--patient", "P7") == 2
    assert "x.png" in capsys.readouterr().err
    np.save(tmp_path / "ok.npy", np.zeros((4, 4), np.uint8))
    assert cli("ingest", str(tmp_path / "ok.npy"), "--patient", "NOPE") == 3
    assert cli("ingest", str(tmp_path / "ok.npy"), "--patient", "P7", "--shape", "4by4") == 2
    assert cli("patient", "add", "P7") == 4
    assert cli("list") == 0
    assert capsys.readouterr().out.strip() == ""


def test_verify_exit_code_on_corruption(
    cli, settings: Settings, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cli("patient", "add", "P7")
    np.save(tmp_path / "f.npy", np.random.default_rng(2).integers(0, 256, (64, 64), np.uint8))
    assert cli("ingest", str(tmp_path / "f.npy"), "--patient", "P7") == 0
    path = next((settings.archive / "raw").rglob("*.h5"))
    with h5py.File(path, "r") as h5:
        ds = h5["frames/0"]
        offset = ds.id.get_chunk_info(0).byte_offset if ds.chunks else ds.id.get_offset()
    with path.open("r+b") as fh:
        fh.seek(offset)
        b = fh.read(1)
        fh.seek(offset)
        fh.write(bytes([b[0] ^ 1]))
    capsys.readouterr()
    assert cli("verify") == 5
    out = capsys.readouterr().out
    assert "problem" in out


def test_commands_refuse_an_unmigrated_catalogue(
    settings: Settings, capsys: pytest.CaptureFixture[str]
) -> None:
    code = main(
        ["--archive", str(settings.archive), "--database-url", settings.database_url, "list"]
    )
    assert code == 6
    assert "rasterserver db upgrade" in capsys.readouterr().err


def test_verify_checks_stored_results_too(
    cli, settings: Settings, processed: str, capsys: pytest.CaptureFixture[str]
) -> None:
    capsys.readouterr()
    assert cli("verify") == 0
    assert "stored results: OK" in capsys.readouterr().out
    derived = sorted((settings.archive / "derived").rglob("*.h5"))
    assert derived
    derived[0].unlink()
    assert cli("verify") == 5
    assert "missing" in capsys.readouterr().out


def test_ingest_with_an_idempotency_key_stores_a_retry_once(
    cli, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cli("patient", "add", "P7")
    np.save(tmp_path / "f.npy", np.random.default_rng(3).integers(0, 256, (32, 32), np.uint8))
    np.save(tmp_path / "g.npy", np.random.default_rng(4).integers(0, 256, (32, 32), np.uint8))
    args = ("ingest", str(tmp_path / "f.npy"), "--patient", "P7", "--idempotency-key", "run-1")
    capsys.readouterr()
    assert cli(*args) == 0
    first = capsys.readouterr().out
    assert cli(*args) == 0
    again = capsys.readouterr().out
    assert first.split()[1] == again.split()[1] and "already stored under this key" in again
    assert cli("ingest", str(tmp_path / "g.npy"), "--patient", "P7",
               "--idempotency-key", "run-1") == 4
    assert "different upload" in capsys.readouterr().err
    assert cli("list", "--json") == 0
    assert len(capsys.readouterr().out.splitlines()) == 1
