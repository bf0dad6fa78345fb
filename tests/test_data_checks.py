"""Training data integrity: which files are runs, the manifest check, the one input check
that train, evaluate and diagnose share, and cut logs."""

from __future__ import annotations

import json
import os
import re

import numpy as np
import pytest

from virtsensor import signals as cat
from virtsensor.cli import main
from virtsensor.errors import UserError
from virtsensor.learning.dataset import load_runs
from virtsensor.recordings.canlog import write_csv, write_log
from virtsensor.recordings.check import check_table
from virtsensor.recordings.manifest import MARKER, file_sha256, start_marker, write_manifest
from virtsensor.recordings.measured import load_measured


def _table(n: int = 200, dt: float = 0.05, seed: int = 0) -> dict[str, np.ndarray]:
    """A plausible 20 Hz table: a car at 20 m/s steering gently (every signal in range)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * dt
    sw = 0.5 * np.sin(2 * np.pi * 0.3 * t + rng.uniform(0, 1))
    vx = np.full(n, 20.0)
    yaw = vx * sw / (14.8 * 2.7 * 1.2)
    tab = {"time_s": t, **{s: np.zeros(n) for s in cat.TABLE_COLUMNS[1:]}}
    tab.update({"steer_angle_rad": sw, "vx_mps": vx, "yaw_rate_radps": yaw, "ay_mps2": yaw * vx,
                "wheel_speed_fl_radps": vx / 0.31, "wheel_speed_fr_radps": vx / 0.31,
                "sat_fl_nm": -30 * sw, "sat_fr_nm": -28 * sw})
    return tab


def _varied_table(n: int = 200, seed: int = 0) -> dict[str, np.ndarray]:
    """:func:`_table` with every input varying a little, as on a car (train refuses a feature that never varies)."""
    tab = _table(n, seed=seed)
    rng = np.random.default_rng(seed + 1000)
    for s in cat.INPUTS:
        tab[s] = tab[s] + rng.uniform(0.0, 0.05, n)
    return tab


def _campaign_dir(d, n_runs: int = 3):
    """A directory as a complete campaign leaves it: runs, then the manifest."""
    d.mkdir()
    start_marker(d, {"preset": "test", "runs": n_runs})
    entries = []
    for i in range(n_runs):
        path = d / f"run{i}.csv"
        write_csv(path, _table(seed=i))
        entries.append({"file": path.name, "manoeuvre": "test", "mu": 1.0, "rows": 200, "sha256": file_sha256(path)})
    write_manifest(d, {"preset": "test", "runs": entries})
    assert not (d / MARKER).exists()
    return d


def _train(capsys, tmp_path, *data) -> tuple[int, str]:
    capsys.readouterr()
    code = main(["train", "--data", *map(str, data), "--out", str(tmp_path / "m.onnx"), "--quiet"])
    err = capsys.readouterr().err.strip()
    assert not (tmp_path / "m.onnx").exists()
    return code, err


# ------------------------------------------------------------------------------------ which files
def test_a_complete_campaign_directory_gives_exactly_its_runs_with_their_metadata(tmp_path):
    d = _campaign_dir(tmp_path / "c")
    (d / ".partial-run9.csv").write_text("time_s\n0.0\n")  # hidden: never a run, never "extra"
    runs = load_runs([d])
    assert [r.name for r in runs] == ["run0", "run1", "run2"]
    assert runs[0].meta["manoeuvre"] == "test" and runs[0].meta["rows"] == 200
    assert [r.name for r in load_runs([d / "run1.csv"])] == ["run1"]


def test_hidden_and_partial_files_are_never_runs(tmp_path, capsys):
    d = tmp_path / "plain"
    d.mkdir()
    write_csv(d / "a.csv", _table())
    write_csv(d / ".partial-b.csv", _table(seed=1))
    write_csv(d / ".hidden.csv", _table(seed=2))
    assert [r.name for r in load_runs([d])] == ["a"]
    code, err = _train(capsys, tmp_path, d / ".partial-b.csv")
    assert code == 2 and "unfinished write" in err and len(err.splitlines()) == 1


def test_a_run_the_directory_seems_to_hold_and_does_not_is_refused(tmp_path, capsys):
    """A link to nothing (a run moved or deleted since) was skipped without a word, and train went on with the
    rest; so would a named pipe. Both refused in one line naming the entry; other suffixes stay ignored."""
    d = tmp_path / "plain"
    d.mkdir()
    write_csv(d / "a.csv", _table())
    (d / "notes.txt").symlink_to(tmp_path / "gone.txt")  # (no recording suffix: not a run, ignored)
    assert [r.name for r in load_runs([d])] == ["a"]
    (d / "b.csv").symlink_to(tmp_path / "moved" / "b.csv")
    code, err = _train(capsys, tmp_path, d)
    assert code == 2 and len(err.splitlines()) == 1, err
    assert err.endswith(f"{d / 'b.csv'}: a link to nothing ({tmp_path / 'moved' / 'b.csv'}): the run it named is "
                        f"gone"), err
    (d / "b.csv").unlink()
    os.mkfifo(d / "c.log")
    with pytest.raises(UserError, match=r"c\.log: not a regular file$"):
        load_runs([d])


def test_a_link_is_judged_by_its_target_not_by_its_own_name_and_folder(tmp_path, capsys):
    """Links in a folder of the user's own made the runs of an unfinished campaign, or a killed campaign's staging
    leftover (``.partial-*``), look like plain recordings: train took them. A link now counts as its target
    would: refused in one line naming the link and the target, given by name or found in a directory; links to
    a complete campaign's listed runs are read, with their manifest entries."""
    unfinished = tmp_path / "unfinished"
    unfinished.mkdir()
    start_marker(unfinished, {"preset": "smoke", "runs": 4})
    for i in range(2):
        write_csv(unfinished / f"run{i}.csv", _table(seed=i))
    write_csv(unfinished / ".partial-run2.csv", _table(seed=2))
    links = tmp_path / "links"
    links.mkdir()
    for i in range(2):
        (links / f"run{i}.csv").symlink_to(unfinished / f"run{i}.csv")
    for given in (links, links / "run0.csv"):
        code, err = _train(capsys, tmp_path, given)
        assert code == 2 and len(err.splitlines()) == 1, err
        assert f"{links / 'run0.csv'} -> {unfinished / 'run0.csv'}: {unfinished}: campaign 'smoke' did not " \
               f"complete" in err, err
    staged = tmp_path / "staged"
    staged.mkdir()
    write_csv(staged / "mine.csv", _table(seed=5))
    (staged / "a.csv").symlink_to(unfinished / ".partial-run2.csv")
    for given in (staged, staged / "a.csv"):
        code, err = _train(capsys, tmp_path, given)
        assert code == 2 and err.endswith(f"{staged / 'a.csv'} -> {unfinished / '.partial-run2.csv'}: an "
                                          f"unfinished write ('.partial-*'), never a recording"), err
    # a complete campaign's runs through links: read as the runs they are; a file it does not list is not one
    c = _campaign_dir(tmp_path / "c")
    good = tmp_path / "good"
    good.mkdir()
    for i in (1, 2):
        (good / f"r{i}.csv").symlink_to(c / f"run{i}.csv")
    runs = load_runs([good])
    assert [r.name for r in runs] == ["r1", "r2"] and runs[0].meta["rows"] == 200
    (good / "r0.csv").symlink_to(c / "run0.csv")
    (c / "run0.csv").write_text((c / "run0.csv").read_text().replace("0.05,", "0.050,", 1))  # (changed since)
    with pytest.raises(UserError, match=r"^\S*r0\.csv -> \S*c/run0\.csv: \S*c/run0\.csv: sha256 .* differs"):
        load_measured([good / "r0.csv"])
    write_csv(c / "stray.csv", _table(seed=7))
    (good / "r0.csv").unlink()
    (good / "r3.csv").symlink_to(c / "stray.csv")
    with pytest.raises(UserError, match=r"r3\.csv -> \S*c/stray\.csv: \S*c/stray\.csv: not listed in"):
        load_runs([good])


@pytest.mark.parametrize("damage, needle", [
    (lambda d: (d / "run1.csv").unlink(), r"run1\.csv: listed in .*manifest\.json but missing"),
    (lambda d: write_csv(d / "stray.csv", _table()), r"stray\.csv: not listed in .*manifest\.json"),
    (lambda d: (d / "notes.txt").write_text("hello"), r"notes\.txt: not listed in .*manifest\.json"),
    (lambda d: (d / "run2.csv").write_text((d / "run2.csv").read_text().replace("0.05,", "0.050,", 1)),
     r"run2\.csv: sha256 [0-9a-f]+\.\.\. differs from the [0-9a-f]+\.\.\. in .*manifest\.json"),
])
def test_a_campaign_directory_that_differs_from_its_manifest_is_refused_naming_the_file(
        tmp_path, capsys, damage, needle):
    d = _campaign_dir(tmp_path / "c")
    damage(d)
    code, err = _train(capsys, tmp_path, d)
    assert code == 2 and len(err.splitlines()) == 1 and re.search(needle, err), err


def test_a_campaign_directory_whose_manifest_is_gone_is_refused_but_a_plain_one_is_read(tmp_path, capsys):
    d = _campaign_dir(tmp_path / "c")
    (d / "manifest.json").unlink()
    code, err = _train(capsys, tmp_path, d)
    assert code == 2 and err.endswith(f"{d}: written by a campaign (.campaign.json) but its manifest.json is "
                                      f"missing, so its runs cannot be verified (rows, sha256); restore the "
                                      f"manifest or run the campaign again"), err
    with pytest.raises(UserError, match=r"manifest\.json is missing"):
        load_measured([d / "run0.csv"])  # a run given by name too
    plain = tmp_path / "plain"  # the same tables as the user's own: no campaign file, read as they are
    plain.mkdir()
    for f in d.glob("*.csv"):
        (plain / f.name).write_bytes(f.read_bytes())
    assert [r.name for r in load_runs([plain])] == ["run0", "run1", "run2"]


def test_manifest_rows_and_entries_are_checked(tmp_path):
    d = _campaign_dir(tmp_path / "c")
    m = json.loads((d / "manifest.json").read_text())
    m["runs"][0]["rows"] = 201
    (d / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(UserError, match=r"run0\.csv: 200 rows read, its manifest lists 201"):
        load_runs([d])
    # a file given by name must be one of the manifest's runs
    write_csv(d / "other.csv", _table())
    with pytest.raises(UserError, match=r"other\.csv: not listed in"):
        load_runs([d / "other.csv"])
    del m["runs"][0]["sha256"]
    (d / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(UserError, match=r"manifest\.json: run 0 \(run0\.csv\) lacks sha256"):
        load_runs([d])


def _drop_run(d, name: str) -> None:
    """What a hand edit leaves: the run's file deleted and its entry taken out of the manifest (nothing else)."""
    (d / name).unlink()
    m = json.loads((d / "manifest.json").read_text())
    m["runs"] = [r for r in m["runs"] if r["file"] != name]
    (d / "manifest.json").write_text(json.dumps(m))


def test_a_run_removed_from_the_manifest_by_hand_is_refused_as_the_campaigns_records_disagree(tmp_path, capsys):
    """A run deleted with its manifest entry left a manifest that checked out run by run: train took the other
    runs (card ``runs: 3``) though the campaign's provenance says it wrote 4 and the manifest's ``samples`` no
    longer adds up. Refused, by directory and by a run's name, in one line naming the disagreement; a manifest
    of a campaign older than the provenance and the ``samples`` total is still read."""
    d = _campaign_dir(tmp_path / "c", n_runs=4)
    m = json.loads((d / "manifest.json").read_text())
    (d / "manifest.json").write_text(json.dumps({**m, "samples": 800}))  # (as a campaign writes it: 4 x 200 rows)
    assert len(load_runs([d])) == 4
    _drop_run(d, "run3.csv")
    code, err = _train(capsys, tmp_path, d)
    assert code == 2 and err.endswith(f"{d}: manifest.json says 800 samples but its 3 runs list 600 rows: it was "
                                      f"changed after the campaign wrote it; run the campaign again"), err
    with pytest.raises(UserError, match=r"says 800 samples but its 3 runs list 600 rows"):
        load_measured([d / "run0.csv"])
    m = json.loads((d / "manifest.json").read_text())
    (d / "manifest.json").write_text(json.dumps({**m, "samples": 600}))  # (the total mended too)
    code, err = _train(capsys, tmp_path, d)
    assert code == 2 and err.endswith(f"{d}: manifest.json lists 3 runs but .campaign.json says the campaign "
                                      f"wrote 4: the manifest was changed after the campaign wrote it; run the "
                                      f"campaign again"), err
    with pytest.raises(UserError, match=r"lists 3 runs but \.campaign\.json says the campaign wrote 4"):
        load_runs([d / "run1.csv"])
    (d / ".campaign.json").write_text("[" * 200_000 + "]" * 200_000)
    with pytest.raises(UserError, match=r"\.campaign\.json: campaign provenance is nested too deeply"):
        load_runs([d])
    (d / ".campaign.json").write_text(json.dumps({"written_by": "virtsensor campaign", "runs": "3"}))
    with pytest.raises(UserError, match=r"\.campaign\.json: not a campaign provenance"):
        load_runs([d])
    (d / ".campaign.json").unlink()  # a campaign written before the provenance and the total: read as it is
    m = json.loads((d / "manifest.json").read_text())
    del m["samples"]
    (d / "manifest.json").write_text(json.dumps(m))
    assert [r.name for r in load_runs([d])] == ["run0", "run1", "run2"]


def test_an_unfinished_campaign_is_refused_in_one_line(tmp_path, capsys):
    d = tmp_path / "c"
    d.mkdir()
    start_marker(d, {"preset": "smoke", "runs": 20})
    write_csv(d / "a.csv", _table())  # one run done (renamed), no manifest yet
    code, err = _train(capsys, tmp_path, d)
    assert code == 2 and len(err.splitlines()) == 1
    assert "campaign 'smoke' did not complete: no manifest.json, 1 of 20 runs written" in err
    with pytest.raises(UserError, match="did not complete"):
        load_measured([d / "a.csv"])


# ----------------------------------------------------------------------------- the input check
def _unsorted(t):
    t["time_s"][[40, 41]] = t["time_s"][[41, 40]]


def _ay_out_of_range(t):
    t["ay_mps2"][57] = 35.0


@pytest.mark.parametrize("change, pattern", [
    (lambda t: t.update(time_s=t["time_s"] * 2),
     r"bad\.csv: column time_s, row 2 \(line 3\): expected 20 Hz rows \(steps of 0\.05 s\), got 10 Hz"),
    (_unsorted, r"bad\.csv: column time_s, row 42 \(line 43\): expected time strictly increasing"),
    (_ay_out_of_range,
     r"bad\.csv: column ay_mps2, row 58 \(line 59\): expected -20 to 20 m/s\^2 or SNA, got 35"),
])
def test_train_refuses_a_bad_table_naming_file_column_and_row_as_diagnose_does(tmp_path, capsys, change, pattern):
    t = _table()
    change(t)
    d = tmp_path / "data"
    d.mkdir()
    write_csv(d / "bad.csv", t)
    code, err = _train(capsys, tmp_path, d)
    assert code == 2 and len(err.splitlines()) == 1 and re.search(pattern, err), err
    with pytest.raises(UserError) as e:
        load_measured([d / "bad.csv"])  # diagnose's reader: the same check, the same words
    assert re.search(pattern, str(e.value)), str(e.value)


def test_simulator_truth_is_not_a_sensor_reading_and_is_not_range_checked():
    t = _table()
    t["kappa_fl_1"] = np.full(200, 3.4)  # a front wheel spinning at low speed on ice: slip ratio > 1
    check_table("sim.csv", t)
    t["tyre_pressure_fl_pa"] = np.full(200, 2.3e5)
    t["tyre_pressure_fl_pa"][0] = -1.0  # an aux signal a car carries is checked
    with pytest.raises(UserError, match=r"column tyre_pressure_fl_pa, row 1 \(line 2\): expected 0 to 510000 Pa"):
        check_table("sim.csv", t)


def test_targets_must_be_finite_for_training_but_a_missing_input_is_sna(tmp_path):
    t = _table()
    t["steer_torque_nm"][10] = np.nan  # SNA: the row is dropped later, the file is fine
    write_csv(tmp_path / "a.csv", t)
    assert len(load_runs([tmp_path / "a.csv"], needed=("steer_torque_nm", "sat_fl_nm"))) == 1
    t["sat_fr_nm"][30] = np.nan
    write_csv(tmp_path / "a.csv", t)
    with pytest.raises(UserError, match=r"a\.csv: column sat_fr_nm, row 31 \(line 32\): expected a finite"):
        load_runs([tmp_path / "a.csv"], needed=cat.OUTPUTS)
    t["sat_fr_nm"][30] = np.inf
    with pytest.raises(UserError, match=r"column sat_fr_nm, row 31: expected -300 to 300 Nm or SNA, got inf"):
        check_table("x.blf", t)


def test_gaps_pass_only_where_allowed(tmp_path):
    t = _table()
    keep = np.ones(200, dtype=bool)
    keep[100:110] = False  # half a second of missing rows
    t = {k: v[keep] for k, v in t.items()}
    check_table("m.csv", t, gaps=True)
    with pytest.raises(UserError, match=r"column time_s, row 101 \(line 102\): expected one 0\.05 s tick after "
                                        r"row 100 .*got a step of 0\.55 s"):
        check_table("m.csv", t)
    t["time_s"][150] += 0.02  # off the tick grid
    with pytest.raises(UserError, match=r"row 151 .*expected a whole number of 0\.05 s ticks"):
        check_table("m.csv", t, gaps=True)


def test_a_gap_of_more_than_a_minute_is_not_one_run_even_where_gaps_are_allowed(tmp_path, capsys):
    """A measured table whose clock jumps 1e7 s (a whole number of ticks) passed as a gap: diagnose then filled
    it with 2e8 NaN rows a column and was killed for memory. Refused naming the row; a 59 s gap still passes."""
    t = _table(n=400)
    t["time_s"][200:] += 59.0
    check_table("m.csv", t, gaps=True)
    t["time_s"][200:] += 1e7 - 59.0
    with pytest.raises(UserError, match=r"^m\.csv: column time_s, row 201 \(line 202\): expected at most 60 s after "
                                        r"row 200 \(at 9\.950000 s; .*got 10000010\.000000 s, 1e\+07 s later$"):
        check_table("m.csv", t, gaps=True)
    write_csv(tmp_path / "jump.csv", t)
    code = main(["diagnose", "--measured", str(tmp_path / "jump.csv"), "--json", str(tmp_path / "d.json"),
                 "--quiet"])
    out, err = capsys.readouterr()
    assert code == 2 and err.count("\n") == 1 and "expected at most 60 s after row 200" in err, err
    assert "Traceback" not in err and not (tmp_path / "d.json").exists()
    long = _table(n=12 * 3600 * 20 + 2)  # one row past 12 h
    with pytest.raises(UserError, match=r"row 864002: expected at most 12 h after row 1 \(at 0\.000000 s; one run "
                                        r"lasts no longer\), got 43200\.050000 s"):
        check_table("x.blf", long)


# --------------------------------------------------------------------------------- cut logs
def _log_signals():
    t = np.arange(0, 3.0, 0.01)
    tab = _table(n=len(t), dt=0.01)
    return t, {k: v for k, v in tab.items() if k in cat.CAN_SIGNALS}


@pytest.mark.parametrize("suffix", [".asc", ".log", ".blf"])
def test_a_log_cut_mid_record_is_refused_with_its_last_good_timestamp(tmp_path, suffix):
    t, sig = _log_signals()
    path = tmp_path / f"run{suffix}"
    write_log(path, t, sig)
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * 0.6) + 3])
    with pytest.raises(UserError) as e:
        load_runs([tmp_path])
    msg = str(e.value)
    assert str(path) in msg and "truncated" in msg and "\n" not in msg
    m = re.search(r"timestamp (\d+\.\d+) s", msg)
    assert m and 0.5 < float(m.group(1)) < 3.0, msg


def test_one_run_given_twice_is_refused_a_copy_or_its_table_beside_its_can_log(tmp_path, capsys):
    """A copy under another name, or the run as a CAN log beside the same run as a table (a campaign written in
    both formats): its files' bytes differ, its signals do not. Counted twice it would weigh double and sit on both
    sides of the held-out split; refused in one line naming both files. Across options (held-out against training)
    check_disjoint refuses it too."""
    import shutil

    from virtsensor.learning.dataset import check_disjoint
    from virtsensor.recordings.files import read_table

    d = tmp_path / "d"
    d.mkdir()
    for i in range(3):
        write_csv(d / f"run{i}.csv", _table(seed=i))
    shutil.copy(d / "run1.csv", d / "zcopy.csv")
    code, err = _train(capsys, tmp_path, d)
    assert code == 2 and err.count("\n") == 0 and "zcopy.csv: the same run as" in err and "run1.csv" in err, err

    t, sig = _log_signals()
    log = tmp_path / "r.blf"
    write_log(log, t, sig)
    write_csv(tmp_path / "r_table.csv", read_table(log))  # (the table of the same frames, as a campaign writes it)
    with pytest.raises(UserError, match=r"r_table\.csv: the same run as .*r\.blf"):
        load_runs([log, tmp_path / "r_table.csv"])
    with pytest.raises(UserError, match=r"given both as --data and as --train-extra \(.*r\.blf, the same content\)"):
        check_disjoint([("--data", load_runs([log])), ("--train-extra", load_runs([tmp_path / "r_table.csv"]))],
                       "a held-out run must not be trained on")
    assert len(load_runs([d / "run0.csv", d / "run1.csv", log])) == 3  # (different runs stay apart)


def test_a_csv_table_cut_mid_row_is_refused(tmp_path):
    path = tmp_path / "a.csv"
    write_csv(path, _table())
    text = path.read_text()
    path.write_text(text[:-7])
    with pytest.raises(UserError, match=r"a\.csv:201: truncated: the file ends inside this row; the last good row "
                                        r"is line 200, time_s 9\.9 s"):
        load_runs([path])


def test_a_csv_that_is_not_utf8_is_refused_in_one_line(tmp_path, capsys):
    path = tmp_path / "bin.csv"
    path.write_bytes(bytes(range(128, 256)) * 4)
    code, err = _train(capsys, tmp_path, path)
    assert code == 2 and err.endswith("not UTF-8 text (byte 0x80 at byte offset 0); a CSV table is UTF-8 text "
                                      "(a binary file or a CAN log named .csv?)") and str(path) in err, err
    with pytest.raises(UserError, match=r"bin\.csv:1: not UTF-8"):
        load_measured([path])


def test_a_cut_mdf4_file_is_refused(tmp_path):
    asammdf = pytest.importorskip("asammdf")
    t = np.arange(0, 5, 0.01)
    mdf = asammdf.MDF(version="4.10")
    mdf.append([asammdf.Signal(np.full_like(t, 20.0), t, name="VehSpeed", unit="m/s")])
    path = tmp_path / "m.mf4"
    mdf.save(path, overwrite=True)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(UserError, match=r"m\.mf4: truncated: .*past the end of the file.*timestamp"):
        load_measured([path])


# ------------------------------------------------------------- runs cut at a line boundary: their metadata's samples
@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    """One short run as ``simulate`` writes it in each line-based format (no trailer that could show a cut), each
    with its metadata ``<stem>.json`` beside it (``file``, ``samples``...)."""
    d = tmp_path_factory.mktemp("simulated")
    for suffix in ("csv", "log", "trc"):
        out = d / f"run-{suffix}.{suffix}"
        assert main(["simulate", "single-sine", "--speed", "60", "--mu", "0.6", "--out", str(out)]) == 0
    return d


def _head(src, dst, meta: dict | None = None) -> None:
    """``head -n <half> src > dst`` (a cut at a line boundary) and, when given, ``meta`` as ``dst``'s ``.json``."""
    lines = src.read_text().splitlines(keepends=True)
    dst.write_text("".join(lines[: len(lines) // 2]))
    if meta is not None:
        dst.with_suffix(".json").write_text(json.dumps(meta))


@pytest.mark.parametrize("suffix", ["csv", "log", "trc"])
def test_a_run_cut_at_a_line_boundary_is_refused_by_the_samples_its_metadata_lists(simulated, tmp_path, capsys,
                                                                                    suffix):
    from virtsensor.assets import model_path

    src = simulated / f"run-{suffix}.{suffix}"
    meta = json.loads(src.with_suffix(".json").read_text())
    cut = tmp_path / f"cut.{suffix}"
    _head(src, cut, {**meta, "file": cut.name})  # its metadata copied with it, as this file's
    pattern = rf"^{re.escape(str(cut))}: (\d+) rows read, its metadata cut\.json lists {meta['samples']} samples"
    for load in (load_runs, load_measured):  # (train, score, evaluate, simulate recorded; diagnose)
        with pytest.raises(UserError) as e:
            load([cut])
        m = re.search(pattern, str(e.value))
        assert m and 0 < int(m.group(1)) < meta["samples"] and "\n" not in str(e.value), str(e.value)
    capsys.readouterr()
    code = main(["score", "--model", str(model_path()), "--data", str(cut), "--json", str(tmp_path / "s.json")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and re.search(pattern[1:], err), err
    assert not (tmp_path / "s.json").exists()


def test_runs_without_their_own_metadata_are_read_as_they_are(simulated, tmp_path):
    """Whole runs with their metadata are read; a run with no metadata of its own (a measured run, one beside
    another run's metadata or beside a JSON of conditions naming no file) cannot show a cut and is read as it is."""
    src = simulated / "run-csv.csv"
    meta = json.loads(src.with_suffix(".json").read_text())
    assert len(load_runs([src])[0].table["time_s"]) == meta["samples"]
    for case, beside in [("measured", None), ("another run's", meta), ("conditions", {"mu": 0.6})]:
        d = tmp_path / case.replace("'", "")
        d.mkdir()
        _head(src, d / "cut.csv", beside)
        n = len(load_runs([d / "cut.csv"])[0].table["time_s"])
        assert 0 < n < meta["samples"], case


def test_a_link_to_a_cut_run_is_refused_by_its_targets_metadata(simulated, tmp_path):
    """A symbolic link is judged by its target: a link (without metadata of its own) to a cut run with its
    metadata is the cut run; a link to a whole run is read."""
    src = simulated / "run-csv.csv"
    meta = json.loads(src.with_suffix(".json").read_text())
    cut = tmp_path / "cut.csv"
    _head(src, cut, {**meta, "file": cut.name})
    (tmp_path / "link.csv").symlink_to(cut)
    (tmp_path / "whole.csv").symlink_to(src)
    link = re.escape(f"{tmp_path / 'link.csv'} -> {cut.resolve()}")
    with pytest.raises(UserError, match=rf"^{link}: \d+ rows read, its metadata cut\.json lists {meta['samples']} "
                                        rf"samples"):
        load_runs([tmp_path / "link.csv"])
    assert len(load_runs([tmp_path / "whole.csv"])[0].table["time_s"]) == meta["samples"]


def test_metadata_whose_samples_is_no_count_is_refused_naming_it(simulated, tmp_path):
    src = simulated / "run-csv.csv"
    meta = json.loads(src.with_suffix(".json").read_text())
    run = tmp_path / "run.csv"
    run.write_bytes(src.read_bytes())
    for bad in ("139", -1, 1.5, True):
        run.with_suffix(".json").write_text(json.dumps({**meta, "file": "run.csv", "samples": bad}))
        with pytest.raises(UserError, match=rf"run\.json: samples {re.escape(repr(bad))} is not a count of rows"):
            load_runs([run])


def test_a_runs_own_metadata_cut_or_damaged_is_refused_not_ignored(simulated, tmp_path):
    """Metadata that names the run as its ``file`` but is no JSON object (cut while written by another tool, damaged)
    would leave a cut run unchecked: refused, naming it. Text that is not JSON and names another file is no one's
    metadata: the run is read as it is."""
    src = simulated / "run-csv.csv"
    meta = json.loads(src.with_suffix(".json").read_text())
    run = tmp_path / "run.csv"
    run.write_bytes(src.read_bytes())
    whole = json.dumps({**meta, "file": "run.csv"})
    for damaged in (whole[: whole.index('"samples"')], whole[:-1], whole.replace(",", ";", 2), "[" + whole):
        run.with_suffix(".json").write_text(damaged)
        with pytest.raises(UserError, match=r"run\.json: the metadata of run\.csv is not a JSON object \(cut or "
                                            r"damaged\)"):
            load_runs([run])
    run.with_suffix(".json").write_text(json.dumps({**meta, "file": "other.csv"})[:-9])
    assert len(load_runs([run])[0].table["time_s"]) == meta["samples"]


def test_whose_metadata_a_json_beside_a_run_is(tmp_path):
    """The one test every reader applies (:func:`virtsensor.recordings.sidecar.sidecar_of`): by its ``file``."""
    from virtsensor.recordings.sidecar import sidecar_of

    run, meta = tmp_path / "run.blf", tmp_path / "run.json"
    assert sidecar_of(run).doc is None and not sidecar_of(run).matches and not sidecar_of(run).foreign  # none
    cases = [  # (content, matches, foreign, usable)
        ({"file": "run.blf", "mu": 0.6}, True, False, True),
        ({"file": "other.blf", "mu": 0.7}, False, True, False),  # another run's: ignored, with a note
        ({"file": None}, False, True, False),
        ({"mu": 0.6}, False, False, True),  # names no file (conditions, a description): used as before
    ]
    for doc, matches, foreign, usable in cases:
        meta.write_text(json.dumps(doc))
        sc = sidecar_of(run)
        assert (sc.matches, sc.foreign, sc.usable is not None) == (matches, foreign, usable), doc
        assert (sc.note is not None) == foreign and (not foreign or f"{meta} ignored" in sc.note)
    for text in ("[1, 2]", "{", "[" * 100_000 + "]" * 100_000, "\udcff", " " * (2 << 20)):  # no object: none
        meta.write_text(text, errors="surrogateescape")
        assert sidecar_of(run).doc is None and sidecar_of(run).note is None


def test_one_run_rounded_to_fewer_decimals_is_still_the_same_run(tmp_path, capsys):
    """A copy re-saved by another tool with 3 decimals has another table digest (values near a half step of the
    CAN resolution round the other way), but it is still the run: refused in training, across --data and
    --train-extra, and among measured runs. A run that differs by two CAN steps at one row, written at full
    precision, is another run; so is a rounded copy one of whose signals was changed beyond the rounding."""
    from virtsensor.learning.dataset import check_disjoint
    from virtsensor.recordings.identity import find_repeat, same_run, table_digest

    a = _table(seed=1)
    a["susp_defl_fl_m"] = 0.004 + 0.002 * np.sin(np.arange(len(a["time_s"])) * 0.37)  # (many values near 0.5e-4)
    rounded = {k: np.round(v, 3) for k, v in a.items()}
    assert table_digest(rounded) != table_digest(a)
    assert same_run(a, rounded) and same_run(rounded, a)
    d = tmp_path / "d"
    d.mkdir()
    write_csv(d / "run0.csv", _table(seed=0))
    write_csv(d / "run1.csv", a)
    write_csv(d / "run1_export.csv", rounded)
    code, err = _train(capsys, tmp_path, d)
    assert code == 2 and err.count("\n") == 0 and "run1_export.csv: the same run as" in err, err
    assert "other decimals" in err and "run1.csv" in err, err
    with pytest.raises(UserError, match=r"given both as --data and as --train-extra \(.*run1\.csv, the same signals"):
        check_disjoint([("--data", load_runs([d / "run0.csv", d / "run1.csv"])),
                        ("--train-extra", load_runs([d / "run1_export.csv"]))], "a held-out run must not be trained on")

    with pytest.raises(UserError, match=r"run1_export\.csv: the same run as .*run1\.csv .*other decimals"):
        load_measured([d / "run1.csv", d / "run1_export.csv"])

    other = {k: v.copy() for k, v in a.items()}
    other["vx_mps"][100] += 0.02  # (two CAN steps of vx at one row, full precision)
    assert not same_run(a, other)
    bent = {k: v.copy() for k, v in rounded.items()}
    bent["steer_angle_rad"][50] += 0.002  # (beyond 3-decimal rounding: another run)
    assert not same_run(a, bent)
    assert find_repeat([_table(seed=i) for i in range(4)]) is None
    assert find_repeat([a, _table(seed=0), rounded]) == (0, 2)
    assert find_repeat([a, rounded], groups=[0, 0]) is None


def test_the_grid_search_never_sees_the_runs_held_out(tmp_path, capsys, monkeypatch):
    """train --grid searched the hyper-parameters by grouped folds over every run, then held runs out and reported
    their score: each held-out run had been a fold's test set, so the score flattered. The search now gets the
    training side only."""
    from virtsensor.features import SPECS
    from virtsensor.learning import training
    from virtsensor.learning.dataset import build_dataset
    from virtsensor.learning.evaluation import grouped_split

    d = tmp_path / "runs"
    d.mkdir()
    for i in range(8):
        write_csv(d / f"r{i}.csv", _varied_table(seed=i))
    seen: list[np.ndarray] = []

    def fake_grid(X, Y, groups, **kw):
        seen.append(np.unique(groups))
        raise ValueError("stopped by the test")

    monkeypatch.setattr(training, "grid_search", fake_grid)
    assert main(["train", "--data", str(d), "--grid", "--recipe", "paper", "--out", str(tmp_path / "m.onnx"),
                 "--quiet", "--seed", "4"]) == 2
    assert "stopped by the test" in capsys.readouterr().err
    ds = build_dataset(load_runs([d]), SPECS[training.RECIPES["paper"]["features"]])
    tr, te = grouped_split(ds.groups, 4)
    assert len(seen) == 1 and set(seen[0]) == set(np.unique(ds.groups[tr]))
    assert not set(seen[0]) & set(np.unique(ds.groups[te])) and len(np.unique(ds.groups[te])) >= 1


def test_a_run_too_short_for_the_features_is_named_not_counted(tmp_path, capsys):
    """A 2-row run gives the improved features no row (their lags need more): train counted it ("5 runs", the
    card too) and trained on the others; score and evaluate already refused it by name."""
    d = tmp_path / "runs"
    d.mkdir()
    for i in range(4):
        write_csv(d / f"r{i}.csv", _table(seed=i))
    write_csv(d / "short.csv", _table(n=2, seed=9))
    code = main(["train", "--data", str(d), "--recipe", "improved", "--out", str(tmp_path / "m.onnx"), "--quiet"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and err.endswith(f"{d / 'short.csv'}: no sample with every input of the 'history' features "
                                      "and both reference SATs finite"), err
    assert not (tmp_path / "m.onnx").exists()


def test_a_blank_line_between_rows_is_refused_so_that_every_line_number_is_right(tmp_path):
    """A blank line was skipped without being counted: every later message named the line before the fault."""
    from virtsensor.recordings.canlog import read_csv

    path = tmp_path / "t.csv"
    write_csv(path, _table())
    lines = path.read_text().splitlines(keepends=True)
    path.write_text("".join(lines) + "\n\n")  # (trailing blank lines end the table: read)
    assert read_csv(path)["time_s"].size == 200
    path.write_text("".join(lines[:40] + ["\n"] + lines[40:]))
    with pytest.raises(UserError, match=rf"^{re.escape(str(path))}:41: a blank line between rows"):
        read_csv(path)


def test_a_folder_of_runs_inside_a_data_folder_is_not_left_out_without_a_word(tmp_path, capsys):
    """score --data nest read nest's two loose runs and skipped the complete campaign in nest/campaignA."""
    d = tmp_path / "nest"
    d.mkdir()
    for i in range(2):
        write_csv(d / f"r{i}.csv", _table(seed=i))
    (d / "plots").mkdir()  # (a folder without recordings: nothing to leave out)
    (d / "plots" / "a.png").write_bytes(b"")
    assert [r.name for r in load_runs([d])] == ["r0", "r1"]
    _campaign_dir(d / "campaignA")
    code, err = _train(capsys, tmp_path, d)
    assert code == 2 and err.endswith(f"{d / 'campaignA'}: a folder of recordings inside {d}, whose folders are not "
                                      "read: give it too, or move it out"), err


def test_a_run_cut_otherwise_is_the_same_run(tmp_path, capsys):
    """A copy of a run without its first row (an export that starts a row later) had another digest and another
    length, so train took it as a second run and evaluate as a circuit never trained on. Now it shares 199 rows
    with the run, at one offset: refused, naming both. Runs that share no stretch are still read."""
    from virtsensor.learning.dataset import check_disjoint

    d = tmp_path / "runs"
    d.mkdir()
    for i in range(3):
        write_csv(d / f"r{i}.csv", _table(seed=i))
    runs = load_runs([d])
    assert len(runs) == 3
    cut = {k: v[1:] for k, v in _table(seed=1).items()}
    write_csv(tmp_path / "trimmed.csv", cut)
    code, err = _train(capsys, tmp_path, d, tmp_path / "trimmed.csv")
    # (149 of the 199: the other rows repeat within the run, a periodic steer at a constant speed, and never count)
    assert code == 2 and err.endswith(f"{tmp_path / 'trimmed.csv'}: 149 of its rows are {d / 'r1.csv'}'s, tick for "
                                      "tick (one run, cut otherwise); a run must count once"), err
    with pytest.raises(UserError, match=r"trimmed\.csv: given both as --data and as --circuits \(149 of its rows are "):
        check_disjoint([("--data", runs), ("--circuits", load_runs([tmp_path / "trimmed.csv"]))], "never trained on")


def test_the_runs_a_model_was_trained_on_are_never_shown_as_unseen(tmp_path, capsys):
    """A model's card now lists the table digests of its training runs. score says which of its runs those are
    (in-sample, not a test); evaluate's and explain's circuits, "never trained on", refuse one."""
    import json

    d = tmp_path / "runs"
    d.mkdir()
    for i in range(4):
        write_csv(d / f"r{i}.csv", _varied_table(seed=i))
    other = tmp_path / "other.csv"
    write_csv(other, _varied_table(seed=11))
    model = tmp_path / "m.onnx"
    assert main(["train", "--data", str(d), "--out", str(model), "--quiet"]) == 0
    card = json.loads(model.with_suffix(".card.json").read_text())
    assert len(card["training_data"]["run_digests"]) == 4
    assert main(["score", "--model", str(model), "--data", str(d / "r2.csv"), str(other), "--json",
                 str(tmp_path / "s.json"), "--markdown", str(tmp_path / "s.md")]) == 0
    assert "1 of these runs the model was trained on" in capsys.readouterr().err
    doc = json.loads((tmp_path / "s.json").read_text())
    assert doc["overall"]["runs_trained_on"] == 1 and [r["trained_on"] for r in doc["runs"]] == [True, False]
    # the figures that are a test, apart: the run never trained on alone (as scored by itself)
    fresh = doc["overall"]["never_trained_on"]
    assert fresh["runs"] == 1 and fresh["n"] == doc["runs"][1]["n"] and fresh["mae_nm"] == doc["runs"][1]["mae_nm"]
    md = (tmp_path / "s.md").read_text()
    assert f"| {d / 'r2.csv'} (trained on) |" in md and f"| {other} |" in md
    assert "**the 1 runs never trained on**" in md and "in-sample, not a test" in md
    for argv in (["evaluate", "--model", str(model), "--data", str(other), "--circuits", str(d / "r2.csv"),
                  "--json", str(tmp_path / "e.json")],
                 ["explain", "--model", str(model), "--data", str(other), "--circuits", str(d / "r2.csv"),
                  "--out", str(tmp_path / "x")]):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert f"{d / 'r2.csv'}: {model} was trained on this run (its card lists it), given as --circuits" in err, err
        assert not (tmp_path / "e.json").exists() and not (tmp_path / "x").exists()


def test_an_unreadable_folder_inside_a_data_folder_holds_nothing_to_leave_out(tmp_path, monkeypatch):
    """A data stick's root-only lost+found: the probe for recordings in it raised PermissionError (exit 1)."""
    from pathlib import Path

    d = tmp_path / "stick"
    d.mkdir()
    write_csv(d / "r0.csv", _table())
    (d / "lost+found").mkdir()
    exists = Path.exists

    def guarded(self, *a, **k):
        if self.parent.name == "lost+found":
            raise PermissionError(13, "Permission denied", str(self))
        return exists(self, *a, **k)

    monkeypatch.setattr(Path, "exists", guarded)
    assert [r.name for r in load_runs([d])] == ["r0"]


def test_an_infinite_value_in_a_simulator_truth_column_is_refused():
    """Truth columns are not range-checked (a slip ratio past 1 is real), but no simulator state is infinite:
    an inf there was read and trained beside."""
    t = _table()
    t["kappa_fl_1"] = np.full(200, 0.01)
    t["kappa_fl_1"][7] = -np.inf
    with pytest.raises(UserError, match=r"sim\.csv: column kappa_fl_1, row 8 \(line 9\): expected a finite value in "
                                        r"1 or SNA \(the simulator's state\), got -inf \(1 rows\)"):
        check_table("sim.csv", t)
    t["kappa_fl_1"][7] = np.nan  # SNA passes
    check_table("sim.csv", t)


def test_train_refuses_a_feature_that_never_varies_naming_it(tmp_path, capsys):
    """A signal constant over every run (a stuck sensor in every recording, a campaign that never changed it) was
    trained on: the scaler divided by a variance of 0 and the model could not learn what it does."""
    d = tmp_path / "runs"
    d.mkdir()
    for i in range(4):
        t = _varied_table(seed=i)
        t["motor_torque_nm"] = np.full(t["time_s"].size, 12.5)
        write_csv(d / f"r{i}.csv", t)
    code = main(["train", "--data", str(d), "--recipe", "paper", "--out", str(tmp_path / "m.onnx"), "--quiet"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and err.count("\n") == 0, err
    assert re.search(r"--data: feature \S*motor_torque\S* of the 'paper' features is 12\.5 in every one of the \d+ "
                     r"rows of 4 run\(s\): a model cannot learn what it does", err), err
    assert not (tmp_path / "m.onnx").exists()


@pytest.mark.parametrize("column", ["ax_mps2", "time_s"])
def test_a_huge_value_gives_the_one_line_and_no_numpy_warning_before_it(tmp_path, capsys, column):
    """1e308 in a bus signal or the time overflowed the run's digest first: a numpy RuntimeWarning (two lines)
    came before the one-line refusal."""
    t = _table()
    t[column][50] = 1e308
    write_csv(tmp_path / "a.csv", t)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # (what the command line shows as lines, raised here)
        code = main(["score", "--data", str(tmp_path / "a.csv"), "--json", str(tmp_path / "o.json")])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and f"column {column}, row 5" in err, err


def test_score_reads_the_can_logs_replay_plays_gzip_text_logs_and_python_cans_csv(tmp_path, capsys):
    """``replay`` and ``demo`` played a ``.asc.gz``/``.log.gz`` log and python-can's CSV CAN log; ``score`` and
    ``train`` refused the first as "unsupported file type '.gz'" and read the second as a table ("unknown column
    'timestamp'"). They read them now, to the same figures as the original log; a .blf.gz stays refused."""
    import can

    src = "sim/data/recordings/random-steer_70kmh_mu0.7_seed4.blf"
    from pathlib import Path

    src = str(Path(__file__).resolve().parent.parent / src)
    maes = []
    for name in ("run.blf", "run.asc.gz", "run.log.gz", "run.csv", "run.csv.gz"):
        with can.LogReader(src) as r, can.Logger(str(tmp_path / name)) as w:
            for m in r:
                w.on_message_received(m)
        out = tmp_path / f"{name}.json"
        assert main(["score", "--data", str(tmp_path / name), "--json", str(out)]) == 0, capsys.readouterr().err
        maes.append(json.loads(out.read_text())["overall"]["mae_nm"])
    assert len(set(maes)) == 1, maes
    from virtsensor.recordings.check import table_error  # (a CSV CAN log's rows are ticks, not its lines)

    assert "(line" not in str(table_error(tmp_path / "run.csv", "ax_mps2", 50, "x", "y"))
    assert "(line 51)" in str(table_error(tmp_path / "table.csv", "ax_mps2", 50, "x", "y"))
    folder = tmp_path / "logs"
    folder.mkdir()
    os.replace(tmp_path / "run.asc.gz", folder / "run.asc.gz")
    assert main(["score", "--data", str(folder), "--json", str(tmp_path / "f.json")]) == 0  # (found in a folder)
    (tmp_path / "x.blf.gz").write_bytes(b"\x1f\x8b")
    capsys.readouterr()
    assert main(["score", "--data", str(tmp_path / "x.blf.gz"), "--json", str(tmp_path / "o.json")]) == 2
    assert "unsupported file type '.gz'" in capsys.readouterr().err
