"""The ``virtsensor`` command line: one entry point, one module per subcommand.

Each subcommand lives in ``virtsensor/commands/<name>.py`` and exposes
``HELP`` (one line), ``add_arguments(parser)`` and ``run(args) -> int``.
Modules are imported only when their subcommand runs, so ``--help`` is fast
and an optional heavy dependency never breaks an unrelated command. Every mistake
is one line on stderr and exit code 2: argparse's (numbers and their ranges, at
parse time), the path arguments' kinds and roles (:func:`~virtsensor.commands._types.check_paths`,
before the command runs: no output overwrites an input, its model card or metadata, or another
output) and the command's own :class:`~virtsensor.errors.UserError`.
:func:`main` returns the exit code (it does not raise ``SystemExit``). A failure of the machine rather than of the
request (a full disk, an I/O error while writing or reading) is one line too, naming the file, with exit code 1;
the outputs are written all or none (:mod:`virtsensor.fileio`), so an existing one keeps its content.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from collections.abc import Sequence

from virtsensor.commands._types import check_paths
from virtsensor.errors import UserError
from virtsensor.extras import MissingExtra, as_user_error, missing_extra
from virtsensor.interrupt import sigint_noted

#: subcommand name -> module under virtsensor.commands, with its one-line help
COMMANDS: dict[str, tuple[str, str]] = {
    "simulate": ("simulate", "simulate a manoeuvre and write a 20 Hz table or a CAN log"),
    "campaign": ("campaign", "simulate a whole data-set preset (e.g. the paper's) in parallel"),
    "replay": ("replay", "play a CAN log (or a simulated manoeuvre) onto a python-can bus"),
    "train": ("train", "train the paper's MLP (or the improved one) on recordings, export ONNX + model card"),
    "evaluate": ("evaluate", "Table IV: the paper's protocols and honest ones, baselines, JSON and Markdown"),
    "score": ("score", "score a shipped model on any recordings, without retraining: R2 and MAE per run"),
    "explain": ("explain", "Section IV.B figures: input correlation, SHAP importance/dependence, track laps"),
    "run": ("run", "the real-time virtual-sensor daemon: CAN in, 20 Hz SAT_FRONT out"),
    "bench": ("bench", "measure the daemon: stage/end-to-end latency, jitter, CPU/RSS, max tick rate, soak"),
    "diagnose": ("diagnose", "sim-to-real: what the simulation gets wrong about measured runs, the cause, the gain"),
    "tyre": ("tyre", "check a .tir tyre property file and print the figures an engineer checks first"),
    "demo": ("demo", "the daemon on a bundled wet-road run: estimated vs true SAT live, then MAE, R2, latency, plot"),
}

#: subcommand name -> the optional extra it needs (see virtsensor.extras); the others run on the base install
COMMAND_EXTRAS: dict[str, str] = {
    "simulate": "train",
    "campaign": "train",
    "train": "train",
    "evaluate": "train",
    "explain": "explain",
    "diagnose": "train",
}


class _Probe(Exception):
    """A mistake argparse found while :func:`_help_or_missing` only asked whether help was wanted."""


class _Parser(argparse.ArgumentParser):
    """argparse with the project's rule for mistakes: one line, exit code 2 (``probing``: raise :class:`_Probe`
    instead, printing nothing)."""

    probing = False

    def error(self, message: str) -> None:  # type: ignore[override]
        if self.probing:
            raise _Probe(message)
        self.exit(2, f"{self.prog}: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    from virtsensor import __version__

    parser = _Parser(
        prog="virtsensor",
        description="virtsensor: real-time virtual sensor of the front tyres' self-aligning torque from CAN signals.",
    )
    parser.add_argument("--version", action="version", version=f"virtsensor {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True
    for name, (module, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.set_defaults(_module=module)
        # Arguments are registered lazily: only the chosen subcommand's module
        # is imported (see main()).
    return parser


def _load(module: str):
    return importlib.import_module(f"virtsensor.commands.{module}")


def _help_or_missing(parser: argparse.ArgumentParser, sub: argparse.ArgumentParser, argv: list[str], name: str,
                     extra: str, missing: MissingExtra) -> int:
    """A command whose optional ``extra`` is not installed (``missing``): its help where argparse finds it asked for
    (``-h``, ``--help``, an abbreviation; printed with the extra to install at its foot, exit 0), else the one line
    that names the extra (exit 2), whatever else the arguments hold."""
    sub.epilog = f"needs the optional extra '{extra}', not installed here: pip install 'virtsensor[{extra}]'"
    probing = [p for p in (parser, sub) if isinstance(p, _Parser)]
    for p in probing:
        p.probing = True
    try:
        parser.parse_args(argv)
    except SystemExit as exc:  # (help or --version printed)
        if exc.code in (0, None):
            return 0
    except _Probe:
        pass
    finally:
        for p in probing:
            p.probing = False
    return _fail(name, missing)


def _fail(command: str, exc: UserError) -> int:
    print(f"virtsensor {command}: error: {_shown(str(exc))}", file=sys.stderr)
    return exc.exit_code


def _shown(text: str) -> str:
    """``text`` as one printable line: a character that is not printable (a newline, an escape sequence, a byte of a
    binary file quoted in a parser's message) is shown escaped (``\\x1b``), never sent to the terminal."""
    if text.isprintable():
        return text
    return "".join(c if c.isprintable() else c.encode("unicode_escape").decode("ascii") for c in text)


def _stdout_gone() -> bool:
    """Whether stdout is a pipe whose reader has closed it (Linux and BSDs: ``poll`` reports an error on it; where
    that cannot be asked, a broken pipe is taken to be stdout's)."""
    try:
        import select

        poller = select.poll()
        poller.register(sys.stdout.fileno(), select.POLLOUT)
        return any(ev & (select.POLLERR | select.POLLHUP) for _, ev in poller.poll(0))
    except (AttributeError, OSError, ValueError):  # (no poll, or no real stdout)
        return True


def _quiet_stdout() -> None:
    """Point stdout at the null device, so that the interpreter's final flush of a closed pipe says nothing."""
    try:
        fd = os.open(os.devnull, os.O_WRONLY)
        os.dup2(fd, sys.stdout.fileno())
        os.close(fd)
    except (OSError, ValueError):  # (no real stdout: nothing to flush)
        pass


def main(argv: Sequence[str] | None = None) -> int:
    """Run one command line; its exit code (0 done, 1 the machine's error, 2 a mistake in the request, 130 a
    Ctrl-C, 143 a SIGTERM where the command turns it into an interrupt)."""
    try:
        return _main(argv)
    except KeyboardInterrupt as exc:  # (a Ctrl-C before the command ran: while its modules load, say)
        print("virtsensor: interrupted", file=sys.stderr)
        return int(getattr(exc, "exit_code", 130))


def _main(argv: Sequence[str] | None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    # First pass: find the subcommand, then let its module add its arguments.
    name = next((a for a in argv if not a.startswith("-")), None)
    sub_action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    if name in COMMANDS:
        extra = COMMAND_EXTRAS.get(name)
        absent = None if extra is None else missing_extra(extra, "this command")
        try:
            mod = _load(COMMANDS[name][0])
            sub = sub_action.choices[name]
            mod.add_arguments(sub)  # (some read their choices from the simulator: their help needs the extra)
            if absent is not None:
                return _help_or_missing(parser, sub, argv, name, str(extra), absent)
        except UserError as exc:
            return _fail(name, exc)
        except ModuleNotFoundError as exc:
            missing = as_user_error(exc, "this command")
            if missing is None:
                raise
            # (every module of the extra that is missing, not only the first one imported)
            return _fail(name, absent if absent is not None else missing)
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse: a mistake (2, one line printed), --help or --version (0)
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 2)
    mod = _load(args._module)
    try:
        # the kind of every path argument (file, directory, writable) and no output over an input, before any work
        check_paths(sub_action.choices[args.command], args)
        with sigint_noted():  # (a Ctrl-C some library swallows still ends the command, nothing written after it)
            return int(mod.run(args) or 0)
    except UserError as exc:
        return _fail(args.command, exc)
    except ModuleNotFoundError as exc:  # an optional path of a base command (e.g. replaying a simulation)
        missing = as_user_error(exc, "this command")
        if missing is None:
            raise
        return _fail(args.command, missing)
    except KeyboardInterrupt as exc:  # Ctrl-C (130), or SIGTERM where a command turns it into one (143)
        print(f"virtsensor {args.command}: interrupted", file=sys.stderr)
        return int(getattr(exc, "exit_code", 130))
    except BrokenPipeError as exc:
        if not _stdout_gone():  # (another pipe, a worker's say: an error like any other)
            return _machine_error(args.command, exc)
        _quiet_stdout()  # the reader of the output left (``| head``): stop quietly, as a Unix filter does
        return 128 + 13  # (the shell's code of a process that SIGPIPE ended)
    except OSError as exc:  # the machine, not the request: a full disk, an I/O error (a worker's, re-raised here)
        return _machine_error(args.command, exc)


def _machine_error(command: str, exc: OSError) -> int:
    """One line for an error of the machine (exit 1)."""
    where = f" ({exc.filename})" if exc.filename else ""
    print(f"virtsensor {command}: error: {exc.strerror or exc}{where}", file=sys.stderr)
    return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
