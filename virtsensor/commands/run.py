"""``virtsensor run``: the real-time virtual-sensor daemon (CAN in, 20 Hz SAT_FRONT and VS_Health out).

Examples::

    virtsensor run --model models/improved.onnx --dbc dbc/virtsensor.dbc --interface socketcan --channel vcan0
    virtsensor run --config /etc/virtsensor/virtsensor.toml --cpu 1 --realtime
    virtsensor run --model m.onnx --interface virtual --channel test --sync-id 0x7F0 --duration 10

Every option can also come from the TOML file given with ``--config`` (same
names, ``-`` or ``_``); options on the command line override the file; an
unknown key in the file is an error. Logs are JSON lines on stderr. SIGTERM or
SIGINT stops it cleanly (exit 0). See ``docs/deployment.md``.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

HELP = "the real-time virtual-sensor daemon: CAN in, 20 Hz SAT_FRONT out"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from virtsensor.commands import _types as t
    from virtsensor.daemon.config import DURATION_MAX_S, INT_RANGES, TIMEOUT_CYCLES_RANGE

    r = INT_RANGES

    parser.add_argument("--model", metavar="FILE.onnx", type=t.existing_file(".onnx"),
                        help="ONNX model (its .card.json beside it; default: the shipped improved model)")
    parser.add_argument("--dbc", metavar="FILE.dbc", type=t.existing_file(".dbc"),
                        help="CAN matrix (default: the bundled dbc/virtsensor.dbc)")
    parser.add_argument("--interface", "-i", help="python-can interface: socketcan, virtual, udp_multicast, pcan...")
    parser.add_argument("--channel", "-c", help="bus channel, e.g. vcan0, can0")
    parser.add_argument("--bitrate", type=t.int_range(*r["bitrate"]), default=None,
                        help="bit rate in bit/s (1000 to 20,000,000), for interfaces that set it")
    parser.add_argument("--sync-id", type=t.can_id(), default=None, metavar="ID",
                        help="tick on frames with this CAN id (e.g. 0x7F0) instead of the free-running 20 Hz clock")
    parser.add_argument("--sync-every", type=t.int_range(*r["sync_every"]), default=None, metavar="N",
                        help="tick on every N-th sync frame (1 to 1000, default 1; e.g. 5 for a 100 Hz input frame)")
    parser.add_argument("--config", metavar="FILE.toml", type=t.text_file(),
                        help="TOML file with any of these settings")
    parser.add_argument("--cpu", type=t.int_range(*r["cpu"]), default=None, metavar="N",
                        help="pin the daemon to CPU N (0 to 4095, one this process may run on)")
    parser.add_argument("--realtime", action=argparse.BooleanOptionalAction, default=None,
                        help="ask for SCHED_FIFO scheduling (logged and ignored when not permitted)")
    parser.add_argument("--rt-priority", type=t.int_range(*r["rt_priority"]), default=None, metavar="P",
                        help="SCHED_FIFO priority (1 to 99; default 50)")
    parser.add_argument("--cpu-latency-us", type=t.int_range(*r["cpu_latency_us"]), default=None, metavar="US",
                        help="hold a Linux PM QoS CPU-latency request (/dev/cpu_dma_latency) of US microseconds "
                             "(0 to 2e9) while running: idle cores stay in states they leave within US (0: poll); "
                             "warmer caches and less wake-up jitter for more idle power (logged and ignored when "
                             "not permitted)")
    parser.add_argument("--duration", type=t.float_range(0.0, DURATION_MAX_S, lo_open=True), default=None, metavar="S",
                        help="stop after S seconds (> 0)")
    parser.add_argument("--timeout-cycles", type=t.float_range(*TIMEOUT_CYCLES_RANGE), default=None, metavar="C",
                        help="an input message is stale after C cycles without a usable frame (1 to 1000; default 3)")
    parser.add_argument("--model-id", type=t.int_range(*r["model_id"]), default=None, metavar="BYTE",
                        help="VS_ModelId byte, 0 to 255 (default: the card's model_id, else its sha256's first byte)")
    parser.add_argument("--log-level", default=None, choices=("debug", "info", "warning", "error"),
                        help="log level (default info)")


def run(args: argparse.Namespace) -> int:
    import signal
    import threading

    from virtsensor.errors import Terminated

    class StoppedBeforeStart(Terminated):
        """SIGTERM while the daemon loads (a supervisor's stop): nothing started, nothing sent, a clean stop."""

        exit_code = 0

    def on_sigterm(signum: int, frame: object) -> None:
        raise StoppedBeforeStart

    main_thread = threading.current_thread() is threading.main_thread()
    before = signal.signal(signal.SIGTERM, on_sigterm) if main_thread else None
    try:
        return _run(args)
    finally:
        if main_thread:
            signal.signal(signal.SIGTERM, before)


def _run(args: argparse.Namespace) -> int:
    import logging

    from virtsensor.daemon import VirtualSensor, configure_logging, load_config, log

    keys = ("model", "dbc", "interface", "channel", "bitrate", "sync_id", "sync_every", "cpu", "realtime",
            "rt_priority", "cpu_latency_us", "duration", "timeout_cycles", "model_id", "log_level")
    cfg = load_config(args.config, {k: getattr(args, k) for k in keys})
    configure_logging(cfg.log_level)
    sensor = VirtualSensor.from_config(cfg)  # refusals (UserError) happen here, before any log line
    if log.isEnabledFor(logging.INFO):
        import hashlib

        from virtsensor.canbus.codec import DEFAULT_DBC

        dbc = Path(cfg.dbc or DEFAULT_DBC)  # (loaded above: the file the daemon decodes with)
        log.info("config", extra={"fields": {**cfg.to_dict(), "dbc": str(dbc),
                                             "dbc_sha256": hashlib.sha256(dbc.read_bytes()).hexdigest(),
                                             "config_file": args.config, "sha256": sensor.model.card.get("sha256")}})
    rc = sensor.run(duration=cfg.duration)
    if _is_main_program():
        # Stopped cleanly: bus closed, shutdown logged. Flush and leave without CPython's finalisation
        # of onnxruntime and cantools, so a supervisor sees the process gone at once.
        logging.shutdown()
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):
                pass
        os._exit(rc)
    return rc


def _is_main_program() -> bool:
    """True when this process is the ``virtsensor`` command itself (console script or ``python -m
    virtsensor.cli``), not a program (e.g. a test) that calls :func:`virtsensor.cli.main`."""
    main = sys.modules.get("__main__")
    spec = getattr(main, "__spec__", None)
    if spec is not None and spec.name in ("virtsensor.cli", "virtsensor"):
        return True
    return os.path.basename(sys.argv[0] if sys.argv else "") == "virtsensor"
