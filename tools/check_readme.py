#!/usr/bin/env python3
"""Run every command of the README as a new user would: fresh clone, new virtual environment.

Every line of the README's ```bash blocks runs in order (a trailing backslash
joins lines), from the root of a fresh ``git clone`` of this repository, with a
new virtual environment first on PATH. Lines that need what this machine lacks
(``sudo``, a SocketCAN interface) are listed as skipped, with the reason.

Usage::

    python tools/check_readme.py                 # everything (about 30 min on 2 cores)
    python tools/check_readme.py --list          # only show the commands
    python tools/check_readme.py --keep DIR      # clone into DIR and keep it

Exit code 0 when every command that ran succeeded; the summary lists each
command with its exit code and wall time.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def commands(readme: Path) -> list[str]:
    """The README's shell commands, in order (continuations joined, comments dropped)."""
    return commands_from_text(readme.read_text())


def commands_from_text(text: str) -> list[str]:
    """The shell commands of Markdown ``text``'s bash blocks."""
    out: list[str] = []
    in_bash = False
    pending = ""
    for line in text.splitlines():
        if line.startswith("```"):
            in_bash = line.strip() in ("```bash", "```sh") and not in_bash
            continue
        if not in_bash:
            continue
        cmd = pending + line.strip()
        if cmd.endswith("\\"):
            pending = cmd[:-1].rstrip() + " "
            continue
        pending = ""
        cmd = re.sub(r"\s+#.*$", "", cmd).strip()
        if cmd and not cmd.startswith("#"):
            out.append(cmd)
    return out


def skip_reason(cmd: str) -> str | None:
    """Why a command cannot run here, or None."""
    if cmd.startswith("sudo ") or " sudo " in cmd:
        return "needs root"
    if "socketcan" in cmd or "vcan0" in cmd:
        if not hasattr(socket, "AF_CAN"):
            return "no SocketCAN on this kernel"
        if not Path("/sys/class/net/vcan0").exists():
            return "no vcan0 interface"
    return None


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--readme", type=Path, default=ROOT / "README.md")
    ap.add_argument("--list", action="store_true", help="print the commands and exit")
    ap.add_argument("--keep", type=Path, help="clone into this (new) directory and keep it")
    args = ap.parse_args(argv)
    cmds = commands(args.readme)
    if args.list:
        for c in cmds:
            print(c)
        return 0
    work = args.keep or Path(tempfile.mkdtemp(prefix="readme-"))
    clone = work / "virtsensor"
    subprocess.run(["git", "clone", "--quiet", str(ROOT), str(clone)], check=True)
    venv = work / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    env = dict(os.environ)
    env["PATH"] = f"{venv / 'bin'}:{env['PATH']}"
    env["VIRTUAL_ENV"] = str(venv)
    env.pop("PYTHONPATH", None)
    results = []
    for cmd in cmds:
        why = skip_reason(cmd)
        if why:
            results.append((cmd, None, 0.0, why))
            print(f"SKIP ({why}): {cmd}", flush=True)
            continue
        print(f"RUN: {cmd}", flush=True)
        t = time.perf_counter()
        rc = subprocess.run(["bash", "-c", cmd], cwd=clone, env=env).returncode
        results.append((cmd, rc, time.perf_counter() - t, ""))
        print(f"  -> exit {rc} in {results[-1][2]:.0f} s", flush=True)
    print("\nsummary:")
    for cmd, rc, dt, why in results:
        print(f"  {'skipped' if rc is None else f'exit {rc}':>8}  {dt:6.0f} s  {cmd}" + (f"  ({why})" if why else ""))
    failed = [r for r in results if r[1] not in (None, 0)]
    if not args.keep:
        shutil.rmtree(work, ignore_errors=True)
    print(f"{len(results) - len(failed)} of {len(results)} fine ({sum(r[1] is None for r in results)} skipped)")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
