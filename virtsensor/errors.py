"""User-facing errors: one clear line, exit code 2, never a traceback."""

from __future__ import annotations


class UserError(Exception):
    """A mistake in what the user asked for or gave us (bad option, bad file).

    The CLI prints ``virtsensor: error: <message>`` on one line and exits 2.
    The message must name what is wrong and where (file, line, option).
    """

    exit_code = 2


class Terminated(KeyboardInterrupt):
    """SIGTERM turned into an interrupt (a command that cleans up as on Ctrl-C): exit code 143 (128 + SIGTERM),
    what the shell reports for a process that SIGTERM ended, where Ctrl-C gives 130."""

    exit_code = 143
