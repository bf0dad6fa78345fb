"""``virtsensor.fileio.staged_dir``: a directory of outputs written all or none."""

from __future__ import annotations

from pathlib import Path

import pytest
from sim_support import recorded_inputs

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
    from virtsensor.commands import simulate as cmd

    def full(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device")

    out = tmp_path / "x.csv"
    out.write_text("an older run\n")
    monkeypatch.setattr(cmd, "write_run_file", full)
    rc = cli.main(["simulate", "steering-pulse", "--speed", "50", "--mu", "0.7", "--out", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 1 and len(err) == 1 and "No space left on device" in err[0] and str(out) in err[0], err
    assert out.read_text() == "an older run\n" and sorted(p.name for p in tmp_path.iterdir()) == ["x.csv"]


def test_a_staged_file_the_block_removes_is_not_written_and_its_target_is_untouched(tmp_path):
    from virtsensor.fileio import staged_files

    (tmp_path / "b.png").write_text("old")
    with staged_files(tmp_path / "a.json", tmp_path / "b.png") as (a, b):
        a.write_text("{}")
        b.unlink()  # (nothing to draw)
    assert (tmp_path / "a.json").read_text() == "{}" and (tmp_path / "b.png").read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.json", "b.png"]


def test_a_staged_writers_own_temporary_file_is_reported_as_its_target(tmp_path):
    """A writer inside the block may write atomically itself (a temporary file of the temporary file): its
    OSError is raised again naming the target the user asked for, not a file that no longer exists."""
    import errno

    from virtsensor.fileio import atomic_write, staged_files

    out = tmp_path / "bench.md"

    def full(p):
        raise OSError(errno.ENOSPC, "No space left on device", str(p))

    with pytest.raises(OSError) as info, staged_files(out) as (tmp,):
        atomic_write(tmp, full)
    assert info.value.filename == str(out) and info.value.errno == errno.ENOSPC
    assert list(tmp_path.iterdir()) == []


def test_simulate_writes_the_run_and_its_metadata_both_or_neither(tmp_path, capsys, monkeypatch):
    """A full disk on the metadata keeps the older run and its metadata as they were; one line, exit 1."""
    import errno

    from virtsensor import cli
    from virtsensor.commands import simulate as cmd

    out, rec = tmp_path / "x.csv", tmp_path / "rec"
    rec.mkdir()
    inputs = str(recorded_inputs(rec, 15.0, n=20))  # a short run: the manoeuvre does not matter here
    assert cli.main(["simulate", "recorded", "--inputs", inputs, "--mu", "0.7", "--out", str(out)]) == 0
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir() if p.is_file()}
    assert sorted(before) == ["x.csv", "x.json"]
    capsys.readouterr()

    def full(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(cmd, "dumps", full)
    assert cli.main(["simulate", "recorded", "--inputs", inputs, "--mu", "0.5", "--out", str(out)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "No space left on device" in err[0] and str(out) in err[0], err
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir() if p.is_file()} == before


def test_a_target_with_the_longest_legal_name_is_staged(tmp_path):
    """The temporary file's name fits the file system however long the target's own (legal) name is."""
    from virtsensor.fileio import NAME_MAX, atomic_write_bytes, write_texts

    a, b = tmp_path / ("a" * (NAME_MAX - 5) + ".json"), tmp_path / ("b" * (NAME_MAX - 3) + ".md")
    write_texts((a, "{}"), (b, "# b"))
    atomic_write_bytes(tmp_path / ("c" * NAME_MAX), b"c")
    assert sorted(len(p.name) for p in tmp_path.iterdir()) == [NAME_MAX] * 3


def test_a_staged_write_that_cannot_start_names_its_target(tmp_path):
    """No folder to put the temporary file in: the error names the output asked for, not a temporary name."""
    import errno

    from virtsensor.fileio import atomic_write_bytes, staged_files

    out = tmp_path / "missing" / "b.md"
    for write in (lambda: atomic_write_bytes(out, b"x"), lambda: staged_files(tmp_path / "a.json", out).__enter__()):
        with pytest.raises(OSError) as info:
            write()
        assert info.value.errno == errno.ENOENT and info.value.filename == str(out)
    assert list(tmp_path.iterdir()) == []


def test_an_error_of_a_file_descriptor_in_a_staged_block_passes_through(tmp_path):
    """An OSError whose "file name" is a descriptor number is raised as it is (no TypeError), nothing left."""
    import errno

    from virtsensor.fileio import staged_files

    with pytest.raises(OSError) as info, staged_files(tmp_path / "q.json"):
        raise OSError(errno.EBADF, "Bad file descriptor", 9999)
    assert info.value.errno == errno.EBADF and list(tmp_path.iterdir()) == []


def test_a_closed_output_pipe_ends_the_command_quietly():
    """``virtsensor ... | head``: when the reader leaves, the command stops with the shell's SIGPIPE code (141)
    and prints nothing more (no "error: Broken pipe", no interpreter message at exit)."""
    import subprocess
    import sys
    from pathlib import Path

    TIR = Path(__file__).resolve().parents[1] / "sim" / "data" / "tyres" / "c_segment_205_55R16.tir"

    code = ("import sys\n"
            "from virtsensor import cli\n"
            "from virtsensor.commands import tyre\n"
            "def talk(args):\n"
            "    for i in range(1_000_000):\n"
            "        print('line', i)\n"
            "tyre.run = talk\n"
            f"sys.exit(cli.main(['tyre', {str(TIR)!r}]))\n")
    p = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    assert p.stdout.readline() == b"line 0\n"
    p.stdout.close()
    err = p.stderr.read().decode()
    assert p.wait(timeout=60) == 141 and err == "", err
    # a broken pipe that is not stdout's (a worker's, say) is an error like any other: one line, exit 1
    other = code.replace("        print('line', i)\n", "        raise BrokenPipeError(32, 'Broken pipe')\n")
    done = subprocess.run([sys.executable, "-c", other], capture_output=True, text=True, timeout=60)
    assert done.returncode == 1 and done.stderr == "virtsensor tyre: error: Broken pipe\n", done.stderr
