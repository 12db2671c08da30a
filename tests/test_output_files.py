"""Output files: refused before the work when they cannot be written; replaced whole or not."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from rasterserver.errors import InputError
from rasterserver.output_files import check_output, check_output_folder, output_file


def _unwritable_folder(tmp_path: Path) -> Path:
    """A folder nothing can be created in: a read-only one, or sysfs when root ignores that."""
    folder = tmp_path / "read-only"
    folder.mkdir()
    folder.chmod(0o555)
    try:
        (folder / "probe").touch()
    except PermissionError:
        return folder
    (folder / "probe").unlink()
    sysfs = Path("/sys")
    try:
        (sysfs / "rasterserver-probe").touch()
    except OSError:
        return sysfs
    pytest.skip("no folder here refuses writes to this user")


def test_a_new_file_is_written_under_a_temporary_name_then_renamed(tmp_path: Path) -> None:
    target = tmp_path / "out.csv"
    with output_file(target) as temp:
        assert temp.parent == tmp_path and temp.suffix == ".csv" and temp != target
        temp.write_text("a,b\n")
        assert not target.exists()  # nothing under the final name until complete
    assert target.read_text() == "a,b\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.csv"]


def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path: Path) -> None:
    target = tmp_path / "out.csv"
    target.write_text("old\n")
    with pytest.raises(RuntimeError), output_file(target) as temp:
        temp.write_text("half")
        raise RuntimeError("writer died")
    assert target.read_text() == "old\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.csv"]


def test_a_writer_that_wrote_nothing_is_an_error(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="nothing was written"), output_file(tmp_path / "x.ply"):
        pass
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    ("name", "message"),
    [
        ("missing/out.ply", "folder .*missing does not exist"),
        ("folder", "is a folder"),
        ("file.txt/out.ply", "Not a directory"),
    ],
)
def test_paths_that_cannot_be_written_are_refused(tmp_path: Path, name: str, message: str) -> None:
    (tmp_path / "folder").mkdir()
    (tmp_path / "file.txt").write_text("x")
    with pytest.raises(InputError, match=message):
        check_output(tmp_path / name)
    with pytest.raises(InputError, match=message), output_file(tmp_path / name):
        pytest.fail("the body must not run")


def test_a_device_is_not_replaced(tmp_path: Path) -> None:
    # as root, a rename over /dev/null would replace the device node
    with pytest.raises(InputError, match="not a regular file"):
        check_output(Path(os.devnull))


def test_an_unwritable_folder_is_refused(tmp_path: Path) -> None:
    folder = _unwritable_folder(tmp_path)
    with pytest.raises(InputError, match="cannot write"):
        check_output(folder / "out.ply")
    with pytest.raises(InputError, match="cannot write"):
        check_output_folder(folder / "new")


def test_output_folders(tmp_path: Path) -> None:
    assert check_output_folder(tmp_path / "a" / "b") == tmp_path / "a" / "b"  # created later
    assert not (tmp_path / "a").exists()  # checking creates nothing
    (tmp_path / "f").write_text("x")
    with pytest.raises(InputError, match="exists and is not a folder"):
        check_output_folder(tmp_path / "f")
    with pytest.raises(InputError, match="is a file, not a folder"):
        check_output_folder(tmp_path / "f" / "sub")
    assert list(tmp_path.iterdir()) == [tmp_path / "f"]  # no probe left behind
