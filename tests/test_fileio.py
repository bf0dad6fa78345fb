"""``virtsensor.fileio.staged_dir``: a directory of outputs written all or none."""

from __future__ import annotations

from pathlib import Path

import pytest

from virtsensor.fileio import staged_dir


def _tree(d: Path) -> dict[str, str]:
    return {str(p.relative_to(d)): (p.read_text() if p.is_file() else "<dir>") for p in sorted(d.rglob("*"))}


def test_a_new_directory_appears_whole(tmp_path):
    out = tmp_path / "a" / "figs"
    with staged_dir(out) as stage:
        (stage / "f1.png").write_text("1")
        assert not out.exists(), "nothing in place before the block ends"
        (stage / "f2.png").write_text("2")
    assert _tree(out) == {"f1.png": "1", "f2.png": "2"}
    assert [p.name for p in tmp_path.rglob(".partial-*")] == []


def test_an_existing_directory_gets_the_new_files_and_keeps_the_rest(tmp_path):
    out = tmp_path / "figs"
    out.mkdir()
    (out / "f1.png").write_text("old")
    (out / "notes.txt").write_text("mine")
    with staged_dir(out) as stage:
        (stage / "f1.png").write_text("new")
    assert _tree(out) == {"f1.png": "new", "notes.txt": "mine"}


@pytest.mark.parametrize("error", [RuntimeError, KeyboardInterrupt])
def test_an_error_or_an_interrupt_leaves_the_directory_as_it_was(tmp_path, error):
    out = tmp_path / "figs"
    out.mkdir()
    (out / "f1.png").write_text("old")
    with pytest.raises(error), staged_dir(out) as stage:
        (stage / "f1.png").write_text("new")
        (stage / "f2.png").write_text("new")
        raise error()
    assert _tree(out) == {"f1.png": "old"}
    assert [p.name for p in tmp_path.iterdir()] == ["figs"], "the staging directory is removed"


def test_a_name_taken_by_a_directory_moves_nothing(tmp_path):
    out = tmp_path / "figs"
    (out / "f2.png").mkdir(parents=True)
    (out / "f1.png").write_text("old")
    with pytest.raises(IsADirectoryError, match="f2.png: is a directory"), staged_dir(out) as stage:
        (stage / "f1.png").write_text("new")
        (stage / "f2.png").write_text("new")
    assert _tree(out) == {"f1.png": "old", "f2.png": "<dir>"}
    assert [p.name for p in tmp_path.iterdir()] == ["figs"]
