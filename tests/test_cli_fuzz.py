"""Every command-line mistake is one line and exit 2: named cases, then a fuzz over every subcommand.

The fuzz draws, for a random subcommand, a random set of its options with values taken from each
option's own type (``fuzz_valid``/``fuzz_invalid`` of :mod:`virtsensor.commands._types`), its
``choices``, or the table of free-text options below, with at least one value that must be refused.
It runs :func:`virtsensor.cli.main` in-process in a scratch directory and asserts exit 2, exactly one
line on stderr, no traceback and nothing written. A refusal that comes only after work has started
(a validation missing or too late) shows as a traceback, a written file or the per-case time limit.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import os
import shlex
import signal
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from virtsensor import cli
from virtsensor.commands import _types as t

#: Free-text options (checked by the command itself): (valid values, values it must refuse).
FREE_TEXT: dict[tuple[str, str], tuple[tuple[str, ...], tuple[str, ...]]] = {
    ("simulate", "manoeuvre"): (("steering-pulse", "magny-cours"), ("nope", "")),
    ("campaign", "preset"): (("tiny",), ("nope", "")),
    ("train", "recipe"): (("paper", "improved"), ("nope",)),
    ("diagnose", "recipe"): (("improved",), ("nope",)),
    ("diagnose", "campaign"): (("smoke",), ("nope",)),
    ("replay", "interface"): (("virtual",), ("nope",)),
    ("replay", "channel"): (("fuzz",), ()),
    ("replay", "manoeuvre"): (("steering-pulse",), ("nope",)),
    ("run", "interface"): (("virtual",), ()),
    ("run", "channel"): (("fuzz",), ()),
}
#: ``--set SECTION.NAME=VALUE`` (simulate, campaign, replay, diagnose).
OVERRIDES = (("vehicle.mass_kg=1500",), ("x", "nope.nope=1", "vehicle.mass_kg=abc", "tyres.file={tmp}/secret.txt"))
PER_CASE_S = 5.0
#: the shipped models
MODELS = Path(__file__).resolve().parents[1] / "models"
IS_ROOT = hasattr(os, "geteuid") and os.geteuid() == 0


@pytest.fixture(scope="module")
def scratch(tmp_path_factory) -> Path:
    """A directory with one of each kind of path the types' examples name."""
    d = tmp_path_factory.mktemp("cli_fuzz")
    (d / "secret.txt").write_text("password = hunter2-SECRET\n")
    (d / "binary.bin").write_bytes(bytes(range(256)) * 4)
    for suffix in (".onnx", ".dbc", ".csv", ".toml", ".png", ".txt"):
        (d / f"file{suffix}").write_bytes(b"not really\n")
        (d / f"dir{suffix}").mkdir()  # a directory where a file of that kind is wanted
    (d / "dir").mkdir()
    (d / "ro").mkdir()
    (d / "ro").chmod(0o555)
    yield d
    (d / "ro").chmod(0o755)


def _usable(text: str) -> bool:
    return not (IS_ROOT and "/ro" in text)  # root writes into read-only directories: not a refusal for root


def _spec(command: str) -> list[dict]:
    """One entry per option/positional of ``command``: flags, nargs, required, valid and invalid values."""
    parser = cli.build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices[command]
    cli._load(cli.COMMANDS[command][0]).add_arguments(sub)
    out = []
    for a in sub._actions:
        if isinstance(a, argparse._HelpAction):
            continue
        entry = {"flag": a.option_strings[0] if a.option_strings else None, "dest": a.dest,
                 "required": a.required or (not a.option_strings and a.nargs is None), "nargs": a.nargs}
        if a.nargs == 0:  # store_true / store_false / BooleanOptionalAction
            entry.update(valid=("",), invalid=())
        elif a.choices is not None:
            entry.update(valid=tuple(map(str, a.choices)), invalid=("nope", ""))
        elif hasattr(a.type, "fuzz_valid"):
            entry.update(valid=a.type.fuzz_valid, invalid=a.type.fuzz_invalid)
        elif a.dest == "overrides":
            entry.update(valid=OVERRIDES[0], invalid=OVERRIDES[1])
        elif (command, a.dest) in FREE_TEXT:
            valid, invalid = FREE_TEXT[(command, a.dest)]
            entry.update(valid=valid, invalid=invalid)
        else:
            raise AssertionError(f"{command} {a.option_strings or a.dest}: no checked type (use virtsensor."
                                 "commands._types), no choices, and not a known free-text option")
        entry["invalid"] = tuple(v for v in entry["invalid"] if _usable(v))
        out.append(entry)
    return out


SPECS = {name: _spec(name) for name in cli.COMMANDS}


def test_every_option_of_every_command_has_a_checked_type():
    """The table above and the types cover every option (``_spec`` raises otherwise); ranges are in the help."""
    for name, spec in SPECS.items():
        assert any(e["invalid"] for e in spec), name
    parser = cli.build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices
    for name in cli.COMMANDS:
        cli._load(cli.COMMANDS[name][0]).add_arguments(sub[name])
        for a in sub[name]._actions:
            name_of = getattr(a.type, "__name__", "")
            if name_of in ("integer", "number") and a.help:
                assert any(w in a.help for w in (" to ", ">", "<")), (name, a.option_strings, a.help)


@st.composite
def bad_argv(draw) -> list[str]:
    """A subcommand's argument list with at least one value its checks must refuse."""
    command = draw(st.sampled_from(sorted(SPECS)))
    spec = SPECS[command]
    chosen = [e for e in spec if e["required"] or draw(st.booleans())]
    candidates = [e for e in chosen if e["invalid"]]
    if not candidates:  # every command has an option with refusable values: add one
        candidates = [draw(st.sampled_from([e for e in spec if e["invalid"]]))]
        chosen.append(candidates[0])
    bad = {id(draw(st.sampled_from(candidates)))}
    bad |= {id(e) for e in candidates if draw(st.integers(0, 9)) == 0}  # now and then a second mistake
    positionals, options = [], []
    for e in chosen:
        pool = e["invalid"] if id(e) in bad else e["valid"]
        n = draw(st.integers(1, 2)) if e["nargs"] == "+" else 1
        values = [draw(st.sampled_from(pool)) for _ in range(n)]
        if e["flag"] is None:
            positionals += values
        elif e["nargs"] == 0:
            options.append([e["flag"]])
        else:
            options.append([e["flag"], *values])
    options = draw(st.permutations(options))
    return [command, *positionals, *(x for o in options for x in o)]


def _alarm(signum, frame):
    raise TimeoutError(f"a case ran over {PER_CASE_S} s: work started before the arguments were checked")


def _run(argv: list[str], where: Path) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    old_cwd = os.getcwd()
    old = signal.signal(signal.SIGALRM, _alarm)
    signal.setitimer(signal.ITIMER_REAL, PER_CASE_S)
    try:
        os.chdir(where)
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            rc = cli.main(argv)
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)
        os.chdir(old_cwd)
    return rc, out.getvalue(), err.getvalue()


def _listing(d: Path) -> list[str]:
    return sorted(str(p.relative_to(d)) for p in d.rglob("*"))


def _assert_refused(argv: list[str], scratch: Path) -> str:
    argv = [a.replace("{tmp}", str(scratch)) for a in argv]
    before = _listing(scratch)
    rc, out, err = _run(argv, scratch)
    shown = shlex.join(argv)
    assert rc == 2, f"{shown}: exit {rc}\n{err}"
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, f"{shown}: stderr is not one line:\n{err}"
    assert "Traceback" not in err and "SECRET" not in err + out, f"{shown}:\n{err}"
    assert _listing(scratch) == before, f"{shown}: wrote {set(_listing(scratch)) - set(before)}"
    return lines[0]


@settings(max_examples=500, deadline=None, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture,
                                 HealthCheck.data_too_large])
@given(argv=bad_argv())
def test_fuzz_every_mistake_is_one_line_and_exit_2(scratch, argv):
    _assert_refused(argv, scratch)


@pytest.mark.parametrize(("argv", "needle"), [
    (["simulate", "steering-pulse", "--speed", "60", "--mu", "1", "--seed", "-1", "--out", "{tmp}/x.csv"], "--seed"),
    (["campaign", "tiny", "--jobs", "0", "--out", "{tmp}/camp"], "--jobs"),
    (["train", "--data", "{tmp}/dir", "--grid-rows", "0", "--out", "{tmp}/m.onnx"], "--grid-rows"),
    (["replay", "{tmp}/file.csv", "-i", "virtual", "-c", "x", "--rate", "1e-300"], "--rate"),
    (["simulate", "steering-pulse", "--speed", "60", "--mu", "1", "--params", "{tmp}/binary.bin",
      "--out", "{tmp}/x.csv"], "binary.bin"),
    (["simulate", "steering-pulse", "--speed", "60", "--mu", "1", "--out", "{tmp}/dir.csv"], "is a directory"),
    (["campaign", "tiny", "--out", "{tmp}/file.txt"], "not a directory"),
    (["explain", "--model", "{tmp}/file.onnx", "--data", "{tmp}/dir", "--out", "{tmp}/file.txt"], "not a directory"),
    (["evaluate", "--model", "{tmp}/dir.onnx", "--data", "{tmp}/dir", "--json", "{tmp}/e.json"], "is a directory"),
    (["train", "--data", "{tmp}/missing", "--out", "{tmp}/m.onnx"], "no such file"),
    (["simulate", "steering-pulse", "--speed", "nan", "--mu", "1", "--out", "{tmp}/x.csv"], "--speed"),
    (["run", "--model-id", "256"], "--model-id"),
    (["bench", "--soak-ticks", "0"], "--soak-ticks"),
    (["demo", "--rate", "0"], "--rate"),
    (["diagnose", "--measured", "{tmp}/dir", "--ensemble", "11"], "--ensemble"),
    # options that do not apply, or exclude each other
    (["bench", "--cpu-latency-us", "5", "--no-cpu-latency"], "not allowed with argument --cpu-latency-us"),
    (["bench", "--cpu-latency-us", "0", "--no-cpu-latency"], "not allowed with argument --cpu-latency-us"),
    (["simulate", "fishhook", "--speed", "60", "--mu", "1", "--longitudinal", "torque", "--out", "{tmp}/x.csv"],
     "--longitudinal goes with the manoeuvre 'recorded' only"),
    (["simulate", "recorded", "--mu", "1", "--inputs", "{tmp}/file.csv", "--laps", "2", "--out", "{tmp}/x.csv"],
     "--laps go with the manoeuvre 'circuit' only"),
    (["replay", "{tmp}/file.csv", "-i", "virtual", "-c", "x", "--mu", "0.5"], "--mu: only for --manoeuvre"),
    (["replay", "{tmp}/file.csv", "-i", "virtual", "-c", "x", "--speed", "60", "--seed", "1", "--set",
      "vehicle.mass_kg=1500"], "--speed, --seed, --set: only for --manoeuvre"),
    (["evaluate", "--model", str(MODELS / "improved.onnx"), "--data", "{tmp}/dir", "--json", "{tmp}/e.json",
      "--tpms-model", str(MODELS / "paper.onnx"), "--pressure-runs", "{tmp}/dir"], "paper.onnx: not a TPMS model"),
    (["simulate", "steering-pulse", "--speed", "60", "--mu", "1", "--set", "tyres.file={tmp}/secret.txt",
      "--out", "{tmp}/x.csv"], "secret.txt"),
])
def test_named_mistakes(scratch, argv, needle):
    line = _assert_refused(argv, scratch)
    assert needle in line, line


def test_a_read_only_output_directory_is_refused(scratch, monkeypatch):
    """(Root writes anywhere, so the directory's mode alone cannot show it: the permission check is faked.)"""
    ro = str(scratch / "ro")
    real = os.access
    monkeypatch.setattr(os, "access", lambda p, mode, **kw: False if str(p).startswith(ro) and mode & os.W_OK
                        else real(p, mode, **kw))
    for argv in (["simulate", "steering-pulse", "--speed", "60", "--mu", "1", "--out", "{tmp}/ro/x.csv"],
                 ["campaign", "tiny", "--out", "{tmp}/ro/camp"],
                 ["explain", "--model", "{tmp}/file.onnx", "--data", "{tmp}/dir", "--out", "{tmp}/ro"]):
        assert "not writable" in _assert_refused(argv, scratch)


def test_train_refuses_a_single_run(scratch, tmp_path):
    from virtsensor import signals as cat

    names = ["time_s", *cat.INPUTS, *cat.OUTPUTS]
    rows = [",".join(["0.05" if n == "time_s" else "0.0" for n in names])] * 3
    run = tmp_path / "run.csv"
    run.write_text(",".join(names) + "\n" + "\n".join(
        ",".join([f"{0.05 * i:.2f}", *r.split(",")[1:]]) for i, r in enumerate(rows)) + "\n")
    line = _assert_refused(["train", "--data", str(run), "--out", "{tmp}/m.onnx"], scratch)
    assert "at least 2" in line


def test_types_refuse_and_accept_their_own_examples(scratch):
    """The examples the fuzz draws from are what the types do (no example is silently the other kind)."""
    import inspect

    makers = [t.int_range(0, 9), t.int_range(1, None), t.jobs(), t.seed(), t.float_range(0.0, 1.0, lo_open=True),
              t.positive_float(), t.rate(), t.can_id(), t.existing_file(".onnx"), t.text_file(), t.existing_dir(),
              t.existing_path(), t.output_file(".csv"), t.output_file(mkdirs=True), t.output_dir(empty=True)]
    assert {n for n, f in inspect.getmembers(t, inspect.isfunction) if not n.startswith("_")} >= {
        "int_range", "float_range", "existing_file", "output_file", "output_dir"}
    def full(fn, text):  # what the CLI applies: the parse-time type, then the path's kind
        value = fn(text)
        getattr(fn, "check_path", lambda _v: None)(value)

    for fn in makers:
        for v in fn.fuzz_valid:
            full(fn, v.replace("{tmp}", str(scratch)))
        for v in fn.fuzz_invalid:
            if _usable(v):
                with pytest.raises(argparse.ArgumentTypeError):
                    full(fn, v.replace("{tmp}", str(scratch)))


def test_every_path_argument_is_an_input_or_an_output():
    """The clash check (an output over an input, or over another output) knows every path argument's role."""
    parser = cli.build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices
    for name in cli.COMMANDS:
        cli._load(cli.COMMANDS[name][0]).add_arguments(sub[name])
        for a in sub[name]._actions:
            if hasattr(a.type, "check_path"):
                assert getattr(a.type, "path_role", None) in (t.INPUT, t.OUTPUT), (name, a.option_strings)


@pytest.fixture()
def inputs(tmp_path) -> Path:
    """Input files of every kind the clash cases read (their content is never read: the refusal comes first)."""
    for name in ("m.onnx", "m.card.json", "run.csv", "run.blf", "tyre.tir"):
        (tmp_path / name).write_text("x\n")
    (tmp_path / "run.json").write_text('{"file": "run.csv"}\n')  # run.csv's metadata, as simulate writes it
    (tmp_path / "camp").mkdir()
    (tmp_path / "camp" / "manifest.json").write_text("{}\n")
    (tmp_path / "rep").mkdir()
    (tmp_path / "link.csv").symlink_to(tmp_path / "run.csv")
    return tmp_path


@pytest.mark.parametrize(("argv", "needle"), [
    # an output over an input, its model card or its metadata sidecar
    (["score", "--model", "{tmp}/m.onnx", "--data", "{tmp}/run.csv", "--json", "{tmp}/run.csv"],
     "--json {tmp}/run.csv would overwrite --data {tmp}/run.csv"),
    (["score", "--model", "{tmp}/m.onnx", "--data", "{tmp}/run.csv", "--json", "{tmp}/m.onnx"], "--model"),
    (["score", "--model", "{tmp}/m.onnx", "--data", "{tmp}/run.csv", "--json", "{tmp}/link.csv"], "--data"),
    (["score", "--model", "{tmp}/m.onnx", "--data", "{tmp}/run.csv", "--json", "{tmp}/m.card.json"],
     "the model card of --model"),
    (["evaluate", "--model", "{tmp}/m.onnx", "--data", "{tmp}/camp", "--json", "{tmp}/m.onnx"], "--model"),
    (["evaluate", "--model", "{tmp}/m.onnx", "--data", "{tmp}/camp", "--json", "{tmp}/e.json",
      "--markdown", "{tmp}/camp/manifest.json"], "lies inside --data"),
    (["tyre", "{tmp}/tyre.tir", "--json", "{tmp}/tyre.tir"], "would overwrite"),
    (["demo", "--recording", "{tmp}/run.blf", "--rate", "max", "--json", "{tmp}/run.blf"], "--recording"),
    (["demo", "--recording", "{tmp}/run.csv", "--rate", "max", "--json", "{tmp}/run.json"], "the metadata of"),
    (["simulate", "recorded", "--mu", "1", "--inputs", "{tmp}/run.csv", "--out", "{tmp}/run.csv"], "--inputs"),
    (["simulate", "recorded", "--mu", "1", "--inputs", "{tmp}/run.csv", "--out", "{tmp}/run.blf"],
     "written with --out"),
    (["diagnose", "--measured", "{tmp}/run.csv", "--json", "{tmp}/run.csv"], "--measured"),
    (["diagnose", "--measured", "{tmp}/run.csv", "--json", "{tmp}/run.json"], "the metadata of --measured"),
    (["bench", "--quick", "--no-cross-process", "--json", "{tmp}/m.onnx", "--model", "{tmp}/m.onnx"], "--model"),
    (["train", "--data", "{tmp}/camp", "--recipe", "tpms", "--fallback", "{tmp}/m.onnx", "--out", "{tmp}/m.onnx"],
     "--fallback"),
    (["train", "--data", "{tmp}/m.card.json", "--out", "{tmp}/m.onnx"], "the model card of --out"),
    (["explain", "--model", "{tmp}/m.onnx", "--data", "{tmp}/camp", "--out", "{tmp}/camp"], "--data"),
    (["explain", "--model", "{tmp}/m.onnx", "--data", "{tmp}/camp", "--out", "{tmp}/camp/figs"], "lies inside"),
    # two outputs on one file, or one inside the other's directory
    (["evaluate", "--model", "{tmp}/m.onnx", "--data", "{tmp}/camp", "--json", "{tmp}/x", "--markdown", "{tmp}/x"],
     "the same file"),
    (["bench", "--json", "{tmp}/x", "--markdown", "{tmp}/x"], "the same file"),
    (["demo", "--plot", "{tmp}/x.png", "--json", "{tmp}/x.png"], "the same file"),
    (["score", "--model", "{tmp}/m.onnx", "--data", "{tmp}/run.csv", "--json", "{tmp}/x", "--markdown", "{tmp}/x"],
     "the same file"),
    (["diagnose", "--measured", "{tmp}/run.csv", "--json", "{tmp}/rep/diagnosis.md", "--report", "{tmp}/rep"],
     "lies inside --report"),
])
def test_an_output_never_overwrites_an_input_or_another_output(inputs, argv, needle):
    line = _assert_refused(argv, inputs)
    assert needle.replace("{tmp}", str(inputs)) in line, line


def test_a_json_beside_a_table_is_no_input_of_a_command_that_never_reads_it(inputs):
    """``score --data run.csv --json run.json`` run twice: the first run's output is no metadata of ``run.csv``
    (metadata names its recording in ``file``), so the second run is not refused."""
    import argparse

    from virtsensor.commands import score

    (inputs / "run.json").write_text('{"overall": {}}\n')  # an earlier score --json
    from virtsensor.commands._types import check_paths

    parser = argparse.ArgumentParser()
    score.add_arguments(parser)
    args = parser.parse_args(["--model", str(inputs / "m.onnx"), "--data", str(inputs / "run.csv"),
                              "--json", str(inputs / "run.json")])
    check_paths(parser, args)  # raises (one line) on a clash


def test_an_output_never_overwrites_the_default_model(inputs, monkeypatch):
    """Without --model the shipped model is read: its card is an input too."""
    monkeypatch.setattr("virtsensor.assets.model_path", lambda name="improved": inputs / "m.onnx")
    line = _assert_refused(["bench", "--json", "{tmp}/m.card.json"], inputs)
    assert "--model (default)" in line, line


@pytest.mark.parametrize(("argv", "companion"), [
    (["simulate", "steering-pulse", "--speed", "60", "--mu", "1", "--out", "{tmp}/new.csv"], "new.json"),
    (["simulate", "steering-pulse", "--speed", "60", "--mu", "1", "--out", "{tmp}/new.blf"], "new.json"),
    (["train", "--data", "{tmp}/camp", "--out", "{tmp}/new.onnx"], "new.card.json"),
])
def test_a_file_written_beside_an_output_must_be_writable_before_any_work(inputs, argv, companion):
    """The metadata of a run, the card of a model: a directory or a read-only file where it goes refuses the command
    in one line before any work, and the output's own file (existing here) is left as it was."""
    out = Path(argv[-1].replace("{tmp}", str(inputs)))
    out.write_text("precious\n")
    (inputs / companion).mkdir()
    line = _assert_refused(argv, inputs)
    assert f"{inputs / companion} (" in line and "is a directory" in line, line
    (inputs / companion).rmdir()
    (inputs / companion).write_text("mine\n")
    (inputs / companion).chmod(0o444)
    if not os.access(inputs / companion, os.W_OK):  # (root writes a read-only file anyway: not refused then)
        line = _assert_refused(argv, inputs)
        assert "is not writable" in line, line
    assert out.read_text() == "precious\n" and (inputs / companion).read_text() == "mine\n"


@pytest.mark.parametrize(("name", "content", "argv", "needle"), [
    ("bin.toml", b"\xff\xfe", ["simulate", "steering-pulse", "--speed", "60", "--mu", "1", "--out", "{tmp}/a.csv",
                               "--params", "{tmp}/bin.toml"], "bin.toml: not UTF-8 text (byte 0)"),
    ("l1.toml", b"x = 1\n\xe9\n", ["campaign", "tiny", "--out", "{tmp}/c", "--params", "{tmp}/l1.toml"],
     "l1.toml: not UTF-8 text (byte 6)"),
    ("h.csv", b"x_m,y_m\n", ["simulate", "circuit", "--track", "{tmp}/h.csv", "--speed", "100", "--mu", "1",
                             "--out", "{tmp}/a.csv"], "h.csv: a closed centreline needs at least 4 distinct points"),
    ("h2.csv", b"x_m,y_m\n\n", ["simulate", "circuit", "--track", "{tmp}/h2.csv", "--speed", "100", "--mu", "1",
                                "--out", "{tmp}/a.csv"], "the file has 0"),
])
def test_an_unreadable_parameter_file_or_an_empty_centreline_is_one_line(tmp_path, name, content, argv, needle):
    (tmp_path / name).write_bytes(content)
    line = _assert_refused(argv, tmp_path)
    assert needle in line, line


@pytest.mark.parametrize(("argv", "needle"), [
    (["tyre", "c_segment_205_55R16", "--set", "LMUY=1e300"], "scaling factor LMUY = 1e+300 is beyond +-100"),
    (["tyre", "c_segment_205_55R16", "--set", "LKY=-101"], "scaling factor LKY = -101 is beyond +-100"),
    (["simulate", "steering-pulse", "--speed", "60", "--mu", "1", "--tyre", "{tmp}/lmuy.tir", "--out",
      "{tmp}/a.csv"], "lmuy.tir:161: scaling factor LMUY = 1e+300 is beyond +-100"),
    # finite and no overflow, but a force of 1e28 times the load, an aligning moment's lever of 95 m: named
    (["tyre", "c_segment_205_55R16", "--set", "PDY1=1e30"], "gives Fy up to 1.83e+28 times the load (over 5), Mz "
     "with a lever of 3.9e+26 m (over the unloaded radius, 0.3135 m) at 0.5-1.5 FNOMIN, 0.9-1.1 INFLPRES, beyond "
     "any tyre: PDY1 = 1e+30; give it a value of a tyre's size"),
    (["simulate", "steering-pulse", "--speed", "60", "--mu", "1", "--tyre", "{tmp}/qdz1.tir", "--out",
      "{tmp}/a.csv"], "qdz1.tir:"),
])
def test_a_tyre_coefficient_no_tyre_has_is_refused_before_any_work(tmp_path, argv, needle):
    from sim.tir import bundled_tir

    text = bundled_tir("c_segment_205_55R16.tir").read_text()
    lines = ["LMUY = 1e300" if ln.split("=")[0].strip() == "LMUY" else ln for ln in text.splitlines()]
    assert lines[160] == "LMUY = 1e300"
    (tmp_path / "lmuy.tir").write_text("\n".join(lines) + "\n")
    lines = ["QDZ1 = 500" if ln.split("=")[0].strip() == "QDZ1" else ln for ln in text.splitlines()]
    (tmp_path / "qdz1.tir").write_text("\n".join(lines) + "\n")
    if "qdz1" in " ".join(argv):
        at = 1 + next(i for i, ln in enumerate(lines) if ln.startswith("QDZ1 "))
        needle = f"qdz1.tir:{at}: the Magic Formula gives Mz with a lever of 95.2 m (over the unloaded radius, " \
                 f"0.3135 m) at 0.5-1.5 FNOMIN, 0.9-1.1 INFLPRES, beyond any tyre: QDZ1 = 500"
    line = _assert_refused(argv, tmp_path)
    assert needle in line, line


def test_a_message_quoting_a_file_never_sends_its_control_characters_to_the_terminal(tmp_path):
    """A parser's message quotes the text it stopped at: an escape sequence there is shown escaped, on one line."""
    (tmp_path / "e.dbc").write_bytes(b'VERSION ""\n\x1b[31mRED\x1b[0m\n')
    line = _assert_refused(["run", "--duration", "1", "-i", "virtual", "-c", "x", "--dbc", "{tmp}/e.dbc"], tmp_path)
    assert "e.dbc: not a valid DBC" in line and "\\x1b[31mRED" in line and "\x1b" not in line, line


@pytest.mark.parametrize(("argv", "needle"), [
    (["simulate", "nosuch", "--mu", "1", "--out", "{tmp}/a.csv"],
     "unknown manoeuvre 'nosuch'; choose one of: free-steer"),  # (not "--speed is required")
    (["replay", "--manoeuvre", "circuit", "-i", "virtual", "-c", "x"],
     "--manoeuvre circuit needs a track, which replay does not take"),
    (["score", "--data", "{tmp}/a.csv", "--json", "-"], "'-' (standard output) is not taken here"),
    (["run", "-i", "virtual", "-c", "x", "--sync-every", "5", "--duration", "0.5"],
     "sync_every 5 goes with sync_id"),  # (an option that would do nothing)
    (["train", "--data", "{tmp}/a.csv", "--out", "{tmp}/m.onnx", "--grid-rows", "500"], "--grid-rows goes with --grid"),
    (["train", "--data", "{tmp}/a.csv", "--out", "{tmp}/m.onnx", "--jobs", "7"], "--jobs goes with --grid"),
])
def test_the_first_thing_wrong_is_the_thing_named(tmp_path, argv, needle):
    (tmp_path / "a.csv").write_text("time_s\n0\n")
    line = _assert_refused(argv, tmp_path)
    assert needle in line, line


def test_explain_refuses_a_directory_where_its_json_goes_before_any_work(tmp_path):
    (tmp_path / "a.csv").write_text("time_s\n0\n")
    (tmp_path / "ex" / "explain.json").mkdir(parents=True)
    line = _assert_refused(["explain", "--data", "{tmp}/a.csv", "--out", "{tmp}/ex"], tmp_path)
    assert f"{tmp_path / 'ex' / 'explain.json'} is a directory" in line, line
