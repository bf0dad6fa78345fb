"""``virtsensor replay``: play a CAN log (or a simulated manoeuvre) onto a python-can bus.

Examples::

    virtsensor replay run.blf --interface socketcan --channel vcan0
    virtsensor replay run.asc --interface virtual --channel test --rate max --quiet
    virtsensor replay --manoeuvre double-lane-change --speed 80 --mu 1.0 --interface socketcan --channel vcan0

Timing follows the log's timestamps (s) scaled by ``--rate``; see
:mod:`virtsensor.recordings.replay`. The log is read through whole before the bus is
opened: a bad log is refused in one line (exit 2) with nothing sent. The closing summary
goes to stdout, the progress bar to stderr.
"""

from __future__ import annotations

import argparse

HELP = "play a CAN log (or a simulated manoeuvre) onto a python-can bus"
#: --speed, --mu and --seed of a simulated manoeuvre when not given
DEFAULT_SPEED_KMH, DEFAULT_MU, DEFAULT_SEED = 80.0, 1.0, 0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from sim.params import MU_RANGE
    from virtsensor.commands import _types as t

    mu_lo, mu_hi = MU_RANGE
    parser.add_argument("file", nargs="?", type=t.existing_file(what="log file"),
                        help="CAN log to play (.blf, .asc, .log, .csv, .trc)")
    parser.add_argument(
        "--interface", "-i", required=True, help="python-can interface, e.g. socketcan, virtual, pcan, vector"
    )
    parser.add_argument("--channel", "-c", required=True, help="bus channel, e.g. vcan0")
    parser.add_argument(
        "--rate", default="1.0", type=t.rate(),
        help="playback speed factor, 0.001 to 1000 (1.0 = real time), or 'max' (as fast as possible)"
    )
    parser.add_argument("--loop", action="store_true", help="start over at the end (Ctrl-C stops)")
    parser.add_argument(
        "--bitrate", type=t.int_range(1000, 20_000_000), default=None,
        help="bit rate in bit/s (1000 to 20,000,000), for interfaces that set it"
    )
    parser.add_argument("--quiet", "-q", action="store_true", help="no progress display")
    sim = parser.add_argument_group("simulated manoeuvre instead of FILE (needs the simulator; these options "
                                    "are refused with a FILE, which plays as recorded)")
    sim.add_argument("--manoeuvre", metavar="NAME", help="manoeuvre to simulate and play")
    sim.add_argument("--speed", metavar="KMH", type=t.positive_float(500.0), default=None,
                     help=f"initial speed in km/h (> 0, the manoeuvre sets the limit; default {DEFAULT_SPEED_KMH:g})")
    sim.add_argument("--mu", metavar="MU", type=t.float_range(mu_lo, mu_hi), default=None,
                     help=f"road friction coefficient ({mu_lo:g} to {mu_hi:g}; default {DEFAULT_MU:g})")
    sim.add_argument("--seed", type=t.seed(), default=None,
                     help=f"simulation seed (0 to 2**32-1; default {DEFAULT_SEED})")
    sim.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.NAME=VALUE",
                     help="override one car parameter (repeatable)")


def run(args: argparse.Namespace) -> int:
    from virtsensor.errors import UserError
    from virtsensor.recordings.replay import check_log, open_bus, parse_rate, replay, simulated_frames

    rate = parse_rate(args.rate)
    if (args.file is None) == (args.manoeuvre is None):
        raise UserError("give either a log FILE or --manoeuvre NAME (not both, not neither)")
    given = [o for o, v in (("--speed", args.speed), ("--mu", args.mu), ("--seed", args.seed),
                            ("--set", args.overrides or None)) if v is not None]
    if args.file is not None and given:
        raise UserError(f"{', '.join(given)}: only for --manoeuvre (a simulated run); the log {args.file} "
                        "plays as it was recorded")
    # Validate the interface name before doing any work.
    import can

    if args.interface not in can.interfaces.VALID_INTERFACES:
        raise UserError(
            f"--interface: unknown interface {args.interface!r}; "
            f"valid: {', '.join(sorted(can.interfaces.VALID_INTERFACES))}"
        )
    if args.manoeuvre is not None:
        source = simulated_frames(args.manoeuvre, speed_kmh=_or(args.speed, DEFAULT_SPEED_KMH),
                                  mu=_or(args.mu, DEFAULT_MU), seed=_or(args.seed, DEFAULT_SEED),
                                  overrides=args.overrides)
    else:
        source = check_log(args.file)  # the whole log, before the bus is opened: a bad one sends nothing
    bus = open_bus(args.interface, args.channel, args.bitrate)
    try:
        summary = replay(source, bus, rate=rate, loop=args.loop, progress=not args.quiet)
    finally:
        bus.shutdown()
    print(summary.format())
    return 130 if summary.interrupted else 0


def _or(value, default):
    """``value``, or ``default`` when the option was not given."""
    return default if value is None else value
