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


def test_staged_files_are_written_all_or_none(tmp_path):
    from virtsensor.fileio import staged_files

    a, b = tmp_path / "a.json", tmp_path / "b.md"
    a.write_text("old a")
    with pytest.raises(RuntimeError), staged_files(a, None, b) as (ta, none, tb):
        assert none is None and ta.parent == tmp_path and ta.suffix == ".json" and tb.suffix == ".md"
        ta.write_text("new a")
        raise RuntimeError("the second output failed")
    assert a.read_text() == "old a" and not b.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.json"]  # (no temporary file left)
    with staged_files(a, b) as (ta, tb):
        ta.write_text("new a")
        tb.write_text("b")
    assert (a.read_text(), b.read_text()) == ("new a", "b")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.json", "b.md"]
    assert a.stat().st_mode & 0o777 == 0o644


def test_a_full_disk_is_one_line_naming_the_file_exit_1(tmp_path, capsys, monkeypatch):
    """A failure of the machine (ENOSPC while writing) is one line naming the output, exit code 1, no traceback,
    no file left, an existing output kept."""
    import errno

    from virtsensor import cli
    from virtsensor.recordings import simulated

    def full(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device")

    out = tmp_path / "x.csv"
    out.write_text("an older run\n")
    monkeypatch.setattr(simulated, "write_run_file", full)
    rc = cli.main(["simulate", "steering-pulse", "--speed", "50", "--mu", "0.7", "--out", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 1 and len(err) == 1 and "No space left on device" in err[0] and str(out) in err[0], err
    assert out.read_text() == "an older run\n" and sorted(p.name for p in tmp_path.iterdir()) == ["x.csv"]
