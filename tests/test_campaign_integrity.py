"""A campaign stopped or killed in the middle: its workers end with it, nothing is written
after, and the directory it leaves is refused by train in one line."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from proc_support import alive as _alive
from proc_support import cpu_s as _cpu_s
from proc_support import descendants as _descendants

from virtsensor.cli import main

pytestmark = pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs /proc to find the workers")


def _snapshot(d: Path) -> dict[str, tuple[int, int]]:
    if not d.exists():
        return {}
    return {f.name: (f.stat().st_size, f.stat().st_mtime_ns) for f in d.iterdir()}


def _start_and_wait_for_work(out: Path) -> tuple[subprocess.Popen, set[int]]:
    """A campaign of four runs on two workers, caught in the middle: once a worker has
    spent a second simulating (past its imports), or has written its first run."""
    # as a terminal's foreground job: SIGINT at its default action (a job started in the background by a
    # non-interactive shell inherits SIGINT ignored, and Python then, rightly, does not turn it into
    # KeyboardInterrupt: run from such a job, this test would send a Ctrl-C the campaign must not see)
    proc = subprocess.Popen([sys.executable, "-m", "virtsensor.cli", "campaign", "tiny", "--out", str(out),
                             "--quiet", "--jobs", "2", "--batch-size", "1"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        workers = _descendants(proc.pid)
        if any(_cpu_s(p) > 1.5 for p in workers) or (
                out.exists() and any(f.name.startswith(".partial-") for f in out.iterdir())):
            break
        assert proc.poll() is None, proc.communicate()
        time.sleep(0.05)
    else:
        os.killpg(proc.pid, signal.SIGKILL)
        pytest.fail("the campaign's workers did not start within 120 s")
    workers = _descendants(proc.pid)
    assert workers, "no worker process under the campaign"
    assert not (out / "manifest.json").exists(), "the campaign ended before the kill"
    return proc, workers


def _assert_all_end_and_nothing_is_written(out: Path, workers: set[int], killed_at: float) -> None:
    deadline = time.monotonic() + 5.0
    while _alive(workers) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not _alive(workers), f"workers still running 5 s after the kill: {sorted(_alive(workers))}"
    before = _snapshot(out)
    for name, (_, mtime) in before.items():
        assert mtime <= killed_at * 1e9, f"{name} written after the kill"
    time.sleep(0.5)
    assert _snapshot(out) == before


@pytest.mark.parametrize("how", ["ctrl-c", pytest.param("sigterm", marks=pytest.mark.slow)])
def test_ctrl_c_or_sigterm_ends_the_whole_campaign_at_once_and_leaves_nothing(tmp_path, how):
    out = tmp_path / "d"
    proc, workers = _start_and_wait_for_work(out)
    if how == "ctrl-c":
        os.killpg(proc.pid, signal.SIGINT)  # what Ctrl-C in a terminal does: the whole foreground group
    else:
        os.kill(proc.pid, signal.SIGTERM)
    try:
        proc.wait(timeout=3.0)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        pytest.fail(f"the campaign did not end within 3 s of {how}")
    ended = time.time()
    _assert_all_end_and_nothing_is_written(out, workers, ended)
    err = proc.stderr.read()
    code = 130 if how == "ctrl-c" else 143  # (128 + the signal, as the shell reports it)
    assert proc.returncode == code and "interrupted" in err and "Traceback" not in err, err
    assert not out.exists()  # it made the directory: it removes it, with every file it wrote


def test_sigkill_of_the_parent_ends_its_workers_and_train_refuses_the_directory(tmp_path, capsys):
    out = tmp_path / "d"
    proc, workers = _start_and_wait_for_work(out)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(timeout=5.0)
    ended = time.time()
    _assert_all_end_and_nothing_is_written(out, workers, ended)
    # what is left: the in-progress marker, maybe unfinished .partial- runs, no manifest, no run
    names = sorted(p.name for p in out.iterdir())
    assert ".campaign-incomplete.json" in names and "manifest.json" not in names
    assert all(n.startswith(".") for n in names), names
    capsys.readouterr()
    assert main(["train", "--data", str(out), "--out", str(tmp_path / "m.onnx"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert str(out) in err and "did not complete" in err and "manifest.json" in err
    assert not (tmp_path / "m.onnx").exists()
    # a .partial- file given by name is never a run
    for partial in (p for p in out.iterdir() if p.name.startswith(".partial-")):
        assert main(["train", "--data", str(partial), "--out", str(tmp_path / "m.onnx"), "--quiet"]) == 2
        assert "unfinished write" in capsys.readouterr().err
    # nor will a new campaign write into it
    assert main(["campaign", "tiny", "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "did not complete" in err or "directory is not empty" in err, err


def test_grid_presets_cover_every_manoeuvre_speed_and_friction_once_deterministically():
    """``paper`` and ``wide`` (the diagnosis' retraining campaign): each Table I manoeuvre at its speeds spread over
    its range, on every friction, one run each, with distinct run seeds, the same for the same campaign seed."""
    from sim.campaign import (
        PAPER_MANOEUVRES,
        PAPER_MU,
        PAPER_SPEEDS_PER_MANOEUVRE,
        PRESETS,
        WIDE_MU,
        WIDE_SPEEDS_PER_MANOEUVRE,
    )
    from sim.manoeuvres import MANOEUVRES

    for name, n_speeds, mus in (("paper", PAPER_SPEEDS_PER_MANOEUVRE, PAPER_MU),
                                ("wide", WIDE_SPEEDS_PER_MANOEUVRE, WIDE_MU)):
        runs = PRESETS[name](3)
        assert len(runs) == len(PAPER_MANOEUVRES) * n_speeds * len(mus)
        assert runs == PRESETS[name](3) and runs != PRESETS[name](4)
        assert len({r.seed for r in runs}) == len(runs)
        for m in PAPER_MANOEUVRES:
            mine = [r for r in runs if r.manoeuvre == m]
            lo, hi = MANOEUVRES[m].speed_kmh
            speeds = sorted({r.speed_kmh for r in mine})
            assert len(speeds) == n_speeds and speeds[0] == pytest.approx(lo, abs=0.05)
            assert speeds[-1] == pytest.approx(hi, abs=0.05)
            assert sorted((r.speed_kmh, r.mu) for r in mine) == sorted((v, mu) for v in speeds for mu in mus)


def test_the_summary_counts_runs_that_did_not_complete_as_planned_by_status():
    """``campaign``'s summary line: how many runs did not complete as planned, by status (OUTCOMES order), so a
    spun or behind-plan run is seen without opening manifest.json."""
    from sim.campaign import outcome_tally

    outcomes = [{"status": "behind-plan", "driven_m": 2128.0, "planned_m": 4285.0}, *[{"status": "spun"}] * 15,
                *[{"status": "completed"}] * 14, {"status": "off-track"}, {"status": "behind-plan"}]
    assert outcome_tally(outcomes) == "18 not completed as planned: 15 spun, 1 off-track, 2 behind-plan"
    assert outcome_tally([{"status": "completed"}] * 3) == outcome_tally([]) == "all completed"


def test_loky_resource_tracker_warnings_are_quiet_only_while_a_campaign_runs(monkeypatch):
    """The processes a campaign starts ignore loky's ``resource_tracker:`` warnings (of the workers it kills on
    purpose); the environment is restored after, filters the user had kept."""
    import os

    from sim.campaign import QUIET_TRACKER, _quiet_resource_tracker

    monkeypatch.delenv("PYTHONWARNINGS", raising=False)
    with _quiet_resource_tracker():
        assert os.environ["PYTHONWARNINGS"] == QUIET_TRACKER
    assert "PYTHONWARNINGS" not in os.environ
    monkeypatch.setenv("PYTHONWARNINGS", "error::DeprecationWarning")
    with _quiet_resource_tracker():
        assert os.environ["PYTHONWARNINGS"].split(",") == ["error::DeprecationWarning", QUIET_TRACKER]
    assert os.environ["PYTHONWARNINGS"] == "error::DeprecationWarning"
    monkeypatch.delenv("PYTHONWARNINGS")
    a, b = _quiet_resource_tracker(), _quiet_resource_tracker()  # (two campaigns in threads, the first ends first)
    a.__enter__()
    b.__enter__()
    a.__exit__(None, None, None)
    assert os.environ["PYTHONWARNINGS"] == QUIET_TRACKER  # (the second still runs)
    b.__exit__(None, None, None)
    assert "PYTHONWARNINGS" not in os.environ
