"""Tests of envs/tools/outdir.py: the --out checks and the atomic write."""

from __future__ import annotations

import pytest
from viotb.envs.tools.outdir import OutDirError, atomic_out_dir, check_out_dir


def test_check_refuses_a_file_and_a_non_empty_folder_unless_overwrite(tmp_path):
    (tmp_path / "f").write_text("x")
    with pytest.raises(OutDirError, match=r"--out .*f is an existing file"):
        check_out_dir(tmp_path / "f")
    with pytest.raises(OutDirError, match="is a file, not a folder"):
        check_out_dir(tmp_path / "f" / "sub")
    with pytest.raises(OutDirError, match="not empty.*--overwrite"):
        check_out_dir(tmp_path)
    assert check_out_dir(tmp_path, overwrite=True) == tmp_path
    assert check_out_dir(tmp_path / "new") == tmp_path / "new"


def test_a_completed_block_appears_at_once_and_replaces_with_overwrite(tmp_path):
    out = tmp_path / "run"
    with atomic_out_dir(out) as tmp:
        (tmp / "a.txt").write_text("1")
        assert not out.exists() and tmp.parent == tmp_path
    assert (out / "a.txt").read_text() == "1"
    with atomic_out_dir(out, overwrite=True) as tmp:
        (tmp / "b.txt").write_text("2")
    assert sorted(p.name for p in out.iterdir()) == ["b.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]


@pytest.mark.parametrize("error", [RuntimeError, KeyboardInterrupt])
def test_an_interrupted_block_leaves_nothing_and_keeps_the_old_folder(tmp_path, error):
    out = tmp_path / "run"
    with atomic_out_dir(out) as tmp:
        (tmp / "old.txt").write_text("old")
    with pytest.raises(error), atomic_out_dir(out, overwrite=True) as tmp:
        (tmp / "half.txt").write_text("half")
        raise error
    with pytest.raises(error), atomic_out_dir(tmp_path / "fresh") as tmp:
        raise error
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]
    assert sorted(p.name for p in out.iterdir()) == ["old.txt"]
