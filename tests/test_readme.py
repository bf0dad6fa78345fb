"""The README's commands: every one parses with today's command line, names only tools/ scripts, modules,
extras and ``virtsensor`` subcommands that exist, and CI runs its test command.

Running them all for real, from a fresh clone in a new virtual environment, is
``python tools/check_readme.py`` (about half an hour, so not part of the suite).
"""

from __future__ import annotations

import argparse
import importlib.util
import re
import shlex
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
_spec = importlib.util.spec_from_file_location("check_readme", ROOT / "tools" / "check_readme.py")
check_readme = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(check_readme)
README = (ROOT / "README.md").read_text()
COMMANDS = check_readme.commands_from_text(README)

_FENCED = re.compile(r"^```.*?^```[^\n]*$", re.S | re.M)
_SPAN = re.compile(r"`([^`]+)`")
_TOOLS_PATH = re.compile(r"(?<![\w/.-])tools/[\w.-]+")
_EXTRAS = re.compile(r"^\.\[([\w,-]+)\]$")


def _parts(cmd: str) -> list[list[str]]:
    """The simple commands of a line (split on &&, |, ; and &)."""
    try:
        tokens = shlex.split(cmd)
    except ValueError:  # an unbalanced quote in prose
        tokens = cmd.split()
    out, cur = [], []
    for tok in tokens:
        if tok in ("&&", "|", ";", "&"):
            out.append(cur)
            cur = []
        else:
            cur.append(tok)
    out.append(cur)
    return [p for p in out if p]


def _declared_extras() -> set[str] | None:
    try:
        import tomllib
    except ImportError:  # Python 3.10
        return None
    with open(ROOT / "pyproject.toml", "rb") as f:
        return set(tomllib.load(f)["project"].get("optional-dependencies", {}))


def _command_problems(cmd: str, *, parse: bool) -> list[str]:
    """What is wrong with one README command: an unknown ``virtsensor`` subcommand (with ``parse``: any
    argument argparse refuses), a ``python``/``bash`` script that is not there, a ``python -m`` module that
    cannot be found, a ``pip install '.[extra]'`` extra that pyproject.toml does not declare."""
    from virtsensor import cli

    out = []
    for part in _parts(cmd):
        head, args = part[0], part[1:]
        if head == "virtsensor" and args and not args[0].startswith("-"):
            name = args[0]
            if name not in cli.COMMANDS:
                out.append(f"unknown virtsensor subcommand {name!r}: {cmd}")
            elif parse:
                parser = cli.build_parser()
                sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
                cli._load(cli.COMMANDS[name][0]).add_arguments(sub.choices[name])
                try:
                    parser.parse_args(args)
                except SystemExit as exc:  # argparse refuses: the README is out of date
                    out.append(f"does not parse (exit {exc.code}): {cmd}")
        elif head in ("python", "python3") and args[:1] == ["-m"] and len(args) > 1:
            module = args[1]
            try:
                found = importlib.util.find_spec(module) is not None
            except ModuleNotFoundError:
                found = False
            if not found:
                out.append(f"no module {module!r}: {cmd}")
            extras = _declared_extras()
            if module == "pip" and extras is not None:
                for tok in args[2:]:
                    m = _EXTRAS.match(tok)
                    for extra in m.group(1).split(",") if m else ():
                        if extra not in extras:
                            out.append(f"extra {extra!r} is not in pyproject.toml: {cmd}")
        elif head in ("python", "python3", "bash", "sh") and args and not args[0].startswith("-"):
            if not (ROOT / args[0]).is_file():
                out.append(f"no script {args[0]}: {cmd}")
    return out


def readme_problems(text: str) -> list[str]:
    """Everything the README ``text`` names that does not exist: its bash blocks' commands (parsed), the
    commands in its inline code (`` `python tools/x.py` ``, `` `virtsensor bench` ``: names only, they may
    carry placeholders), any ``tools/...`` path and the files of its ``tools/`` table row."""
    out = []
    for cmd in check_readme.commands_from_text(text):
        out += _command_problems(cmd, parse=True)
    prose = _FENCED.sub("", text)
    for span in _SPAN.findall(prose):
        out += _command_problems(" ".join(span.split()), parse=False)
    for rel in sorted(set(_TOOLS_PATH.findall(text))):
        if not (ROOT / rel).is_file():
            out.append(f"no file {rel}")
    for rel in _tools_row(prose):
        if not (ROOT / rel).is_file():
            out.append(f"no file {rel} (the tools/ row of the layout table)")
    return out


def _tools_row(text: str) -> list[str]:
    """The files the README's layout table lists in its ``tools/`` row."""
    return [f"tools/{name}" for line in text.splitlines() if line.startswith("| `tools/` |")
            for name in _SPAN.findall(line.split("|")[2])]


def test_quickstart_is_two_commands_and_ci_runs_the_test_one():
    quick = README.split("## Quickstart", 1)[1].split("\n## ", 1)[0]
    blocks = check_readme.commands_from_text(quick)
    assert len(blocks) == 2, blocks
    assert "virtsensor demo" in blocks[0] and "pip install" in blocks[0]
    assert "pytest" in blocks[1] and "pip install" in blocks[1]
    ci = (ROOT / ".ci" / "run").read_text().splitlines()
    marker = ci.index("# --- the README's test command, verbatim ---")
    assert ci[marker + 1] == blocks[1]


@pytest.mark.parametrize("cmd", COMMANDS)
def test_every_readme_command_parses(cmd):
    assert _command_problems(cmd, parse=True) == []


def test_the_readme_names_only_tools_and_subcommands_that_exist():
    assert readme_problems(README) == []


def _broken(pattern: str, repl: str) -> tuple[str, str]:
    """The README text with the first match of ``pattern`` replaced, and the replacement."""
    m = re.search(pattern, README, flags=re.M)
    assert m, f"the README no longer has {pattern!r}: pick another example for this test"
    new = m.expand(repl)
    return README[:m.start()] + new + README[m.end():], new


@pytest.mark.parametrize(("pattern", "repl", "named"), [
    (r"^(python -m pip install .*&& virtsensor) (\w+)", r"\1 \2x", r"subcommand '\w+x'"),  # a bash block
    (r"`virtsensor (\w+)", r"`virtsensor \1x", r"subcommand '\w+x'"),                     # inline code
    (r"`python (tools/[\w-]+)\.py", r"`python \1x.py", r"no script tools/[\w-]+x\.py"),
    (r"`bash (tools/[\w-]+)\.sh", r"`bash \1x.sh", r"no script tools/[\w-]+x\.sh"),
    (r"^(\| `tools/` \| `[\w-]+)(\.\w+`)", r"\1x\2", r"no file tools/[\w-]+x\.\w+ \(the tools/ row"),
    (r"'\.\[(\w+)\]'", r"'.[\1x]'", r"extra '\w+x' is not in pyproject"),
])
def test_the_readme_check_catches_what_does_not_exist(pattern, repl, named):
    """The check above is not vacuous: naming a tools/ script, subcommand or extra that does not exist, in
    a copy of the README, is reported."""
    if "extra" in named and _declared_extras() is None:
        pytest.skip("reading pyproject.toml needs tomllib (Python >= 3.11)")
    text, new = _broken(pattern, repl)
    problems = readme_problems(text)
    assert any(re.search(named, p) for p in problems), (new, problems)


def _not_committed(rels) -> list[str]:
    """Those of ``rels`` that ``git ls-files`` does not list, or that are not in the working tree
    (skips when there is no git or no checkout)."""
    if shutil.which("git") is None:
        pytest.skip("git is not installed: cannot tell which files are committed")
    r = subprocess.run(["git", "-C", str(ROOT), "ls-files", "-z"], capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"{ROOT} is not a git checkout, cannot tell which files are committed: {r.stderr.strip()}")
    tracked = set(r.stdout.split("\0"))
    return sorted(rel for rel in set(rels) if rel not in tracked or not (ROOT / rel).is_file())


def test_files_the_readme_relies_on_are_shipped():
    """Committed, not merely present in this working tree (a fresh clone would lack them)."""
    relied = ["dbc/virtsensor.dbc", "models/improved.onnx", "models/paper.onnx", "models/evaluation.md",
              "docs/deployment.md", "NOTICE", ".ci/run", "tools/check_readme.py",
              *_TOOLS_PATH.findall(README), *_tools_row(README)]
    assert _not_committed(relied) == []
