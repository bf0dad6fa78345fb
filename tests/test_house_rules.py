"""House rules that a review would otherwise have to catch: sizes and the direction of dependencies."""

from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LIBRARY = [p for p in (ROOT / "virtsensor").rglob("*.py") if "commands" not in p.parts and p.name != "cli.py"]


def test_no_function_over_80_lines_and_no_class_over_300_in_the_package():
    too_long = []
    for path in (ROOT / "virtsensor").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            n = node.end_lineno - node.lineno + 1 if hasattr(node, "end_lineno") else 0
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and n > 80:
                too_long.append(f"{path.relative_to(ROOT)}:{node.lineno} def {node.name} ({n} lines)")
            if isinstance(node, ast.ClassDef) and n > 300:
                too_long.append(f"{path.relative_to(ROOT)}:{node.lineno} class {node.name} ({n} lines)")
    assert too_long == []


def test_the_library_and_the_simulator_never_import_the_command_line():
    pattern = re.compile(r"^\s*(from virtsensor\.commands|import virtsensor\.commands|from virtsensor\.cli |"
                         r"import virtsensor\.cli|from virtsensor import cli)", re.M)
    offenders = [str(p.relative_to(ROOT)) for p in [*LIBRARY, *(ROOT / "sim").rglob("*.py")]
                 if pattern.search(p.read_text(encoding="utf-8"))]
    assert offenders == []
