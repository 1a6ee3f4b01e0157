"""Output paths: checked before the work, written whole."""

import os
import stat
from pathlib import Path

import pytest

from beamctl.common import outputs
from beamctl.common.outputs import OutputPathError, check_dir, check_file, replacing, write_text

# Tests run as root, for whom permission bits stop nothing: /sys refuses new files to everyone.
UNWRITABLE = Path("/sys")


def _refusal(check, path, what="--out") -> str:
    with pytest.raises(OutputPathError) as info:
        check(path, what)
    message = str(info.value)
    assert message.startswith(f"{what} {path}: cannot write there ("), message
    assert "\n" not in message
    return message


def _tree(root: Path) -> list[str]:
    return sorted(str(p.relative_to(root)) for p in root.rglob("*"))


def test_a_directory_is_not_a_file(tmp_path):
    assert "it is a directory" in _refusal(check_file, tmp_path)


def test_a_file_is_not_a_directory(tmp_path):
    (tmp_path / "f").write_text("")
    assert "it is a file, not a directory" in _refusal(check_dir, tmp_path / "f")


@pytest.mark.parametrize("check", [check_file, check_dir])
def test_a_file_cannot_be_a_parent_directory(tmp_path, check):
    (tmp_path / "f").write_text("")
    message = _refusal(check, tmp_path / "f" / "sub" / "x.yaml")
    assert f"{tmp_path / 'f'} is not a directory" in message


@pytest.mark.parametrize("check", [check_file, check_dir])
@pytest.mark.parametrize("path", [UNWRITABLE / "beamctl.out", UNWRITABLE / "beamctl-missing" / "x.out"])
def test_a_place_nobody_may_write_is_refused(check, path):
    message = _refusal(check, path)
    assert "permission denied" in message or "read-only" in message, message
    assert not path.exists()


def test_a_missing_parent_that_can_be_created_is_accepted_and_not_left_behind(tmp_path):
    assert check_file(tmp_path / "a" / "b" / "t.yaml", "--out") == tmp_path / "a" / "b" / "t.yaml"
    assert check_dir(tmp_path / "c" / "d", "--plot") == tmp_path / "c" / "d"
    assert _tree(tmp_path) == [], "the check creates nothing that stays"


def test_a_refused_check_removes_the_directories_it_created(tmp_path, monkeypatch):
    def refuse(target):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(outputs, "_temporary", refuse)
    assert "permission denied" in _refusal(check_dir, tmp_path / "a" / "b" / "c")
    assert _tree(tmp_path) == []


def test_an_existing_file_and_a_device_are_accepted(tmp_path):
    (tmp_path / "t.yaml").write_text("old")
    assert check_file(tmp_path / "t.yaml", "--out") == tmp_path / "t.yaml"
    assert check_file("/dev/null", "--out") == Path("/dev/null")
    assert _tree(tmp_path) == ["t.yaml"]


def test_replacing_moves_the_whole_file_into_place_with_the_old_mode(tmp_path):
    target = tmp_path / "t.yaml"
    target.write_text("old")
    target.chmod(0o640)
    with replacing(target) as temp:
        assert temp.parent == tmp_path and temp.suffix == ".yaml" and temp != target
        temp.write_text("new")
        assert target.read_text() == "old", "the old file stays until the new one is complete"
    assert target.read_text() == "new"
    assert stat.S_IMODE(target.stat().st_mode) == 0o640
    assert _tree(tmp_path) == ["t.yaml"]


@pytest.mark.parametrize("error", [KeyboardInterrupt, OSError])
def test_an_interrupted_write_leaves_the_old_file_and_no_temporary(tmp_path, error):
    target = tmp_path / "t.yaml"
    target.write_text("old")
    with pytest.raises(error), replacing(target) as temp:
        temp.write_text("half a ta")
        raise error()
    assert target.read_text() == "old"
    assert _tree(tmp_path) == ["t.yaml"]


def test_a_new_file_gets_the_umask_s_mode(tmp_path):
    umask = os.umask(0o022)
    try:
        write_text(tmp_path / "summary.txt", "x")
    finally:
        os.umask(umask)
    assert stat.S_IMODE((tmp_path / "summary.txt").stat().st_mode) == 0o644
