"""The README's commands: every one parses with today's command line, and CI runs its test command.

Running them all for real, from a fresh clone in a new virtual environment, is
``python tools/check_readme.py`` (about half an hour, so not part of the suite).
"""

from __future__ import annotations

import argparse
import importlib.util
import shlex
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
_spec = importlib.util.spec_from_file_location("check_readme", ROOT / "tools" / "check_readme.py")
check_readme = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(check_readme)
COMMANDS = check_readme.commands(ROOT / "README.md")


def _parts(cmd: str) -> list[list[str]]:
    """The simple commands of a line (split on && and |)."""
    out, cur = [], []
    for tok in shlex.split(cmd):
        if tok in ("&&", "|", ";"):
            out.append(cur)
            cur = []
        else:
            cur.append(tok)
    out.append(cur)
    return [p for p in out if p]


def test_quickstart_is_two_commands_and_ci_runs_the_test_one():
    text = (ROOT / "README.md").read_text()
    quick = text.split("## Quickstart", 1)[1].split("\n## ", 1)[0]
    blocks = check_readme.commands_from_text(quick)
    assert len(blocks) == 2, blocks
    assert "virtsensor demo" in blocks[0] and "pip install" in blocks[0]
    assert "pytest" in blocks[1] and "pip install" in blocks[1]
    ci = (ROOT / ".ci" / "run").read_text().strip().splitlines()[-1]
    assert ci == blocks[1]


@pytest.mark.parametrize("cmd", [c for c in COMMANDS if "virtsensor " in c or "tools/" in c])
def test_every_readme_command_parses(cmd):
    from virtsensor import cli

    for part in _parts(cmd):
        if part[0] == "virtsensor":
            argv = part[1:]
            parser = cli.build_parser()
            name = argv[0]
            assert name in cli.COMMANDS, f"unknown subcommand in README: {cmd}"
            sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
            cli._load(cli.COMMANDS[name][0]).add_arguments(sub.choices[name])
            try:
                parser.parse_args(argv)
            except SystemExit as exc:  # argparse refuses: the README is out of date
                pytest.fail(f"README command does not parse ({exc.code}): {cmd}")
        elif part[0] in ("python", "python3", "bash") and len(part) > 1 and not part[1].startswith("-"):
            assert (ROOT / part[1]).exists(), f"README names a missing script: {part[1]}"


def test_files_the_readme_relies_on_are_shipped():
    for rel in ("dbc/virtsensor.dbc", "models/improved.onnx", "models/paper.onnx", "models/evaluation.md",
                "docs/deployment.md", "NOTICE"):
        assert (ROOT / rel).exists(), rel
