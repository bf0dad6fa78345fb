"""``virtsensor bench``: the daemon's latency, jitter, throughput, CPU/RSS and soak figures.

Examples::

    virtsensor bench --json bench.json --markdown bench.md --histogram bench.png
    virtsensor bench --model m.onnx --quick
    virtsensor bench --soak-ticks 10000

See :mod:`virtsensor.daemon.bench` for what each figure measures.
"""

from __future__ import annotations

import argparse
import sys

HELP = "measure the daemon: per-stage and end-to-end latency, jitter, CPU/RSS, max tick rate, soak"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from virtsensor.assets import model_path
    from virtsensor.commands import _types as t

    parser.add_argument("--model", metavar="FILE.onnx", default=None,
                        type=t.existing_file(".onnx", implicit=model_path),
                        help="ONNX model (its .card.json beside it; default: the shipped improved model)")
    parser.add_argument("--json", metavar="FILE", type=t.output_file(), help="write the figures as JSON")
    parser.add_argument("--markdown", metavar="FILE", type=t.output_file(), help="write a Markdown summary")
    parser.add_argument("--histogram", metavar="PNG", type=t.output_file(".png"),
                        help="write a histogram of the tick compute times")
    parser.add_argument("--quick", action="store_true", help="small counts everywhere (a few seconds)")
    parser.add_argument("--soak-ticks", type=t.int_range(1, 10**8), default=None, metavar="N",
                        help="ticks of the soak (1 to 10**8; default 72000 = one hour at 20 Hz; --quick: 1000)")
    parser.add_argument("--no-cross-process", action="store_true",
                        help="skip the udp_multicast run in a private network namespace")
    latency = parser.add_mutually_exclusive_group()
    latency.add_argument("--cpu-latency-us", type=t.int_range(0, 2_000_000_000), default=None, metavar="US",
                         help="PM QoS CPU-latency request (0 to 2e9 us) of the free-running daemon (as virtsensor "
                              "run --cpu-latency-us; default 0); it is also measured without one")
    latency.add_argument("--no-cpu-latency", action="store_true",
                         help="measure the free-running daemon with the machine's idle policy only (not with "
                              "--cpu-latency-us)")
    parser.add_argument("--quiet", "-q", action="store_true", help="no progress on stderr")


def run(args: argparse.Namespace) -> int:
    from virtsensor.daemon.bench import run_bench, to_json, write_histogram, write_markdown
    from virtsensor.fileio import staged_files
    from virtsensor.interrupt import sigterm_interrupts

    def say(text: str) -> None:
        if not args.quiet:
            print(f"bench: {text}", file=sys.stderr, flush=True)

    if args.histogram:
        from virtsensor import plotting

        plotting.require("--histogram")  # (before minutes of measuring, not after)
    with sigterm_interrupts():  # (a supervisor's stop ends the cross-process daemon and its files, as Ctrl-C)
        r = run_bench(args.model, quick=args.quick, soak_ticks=args.soak_ticks,
                      cross_process=not args.no_cross_process, progress=say,
                      cpu_latency_us=None if args.no_cpu_latency else args.cpu_latency_us or 0)
        text = to_json(r)
        with staged_files(args.json, args.markdown, args.histogram) as (json_tmp, md_tmp, hist_tmp):  # (all or none)
            if json_tmp is not None:
                json_tmp.write_text(text, encoding="utf-8")
            if md_tmp is not None:
                write_markdown(r, md_tmp)
            if hist_tmp is not None:
                write_histogram(r, hist_tmp)
    t = r["targets"]
    for k, v in t.items():
        say(f"{k}: {v['value']} ({v['limit']}) {'met' if v['met'] else 'MISSED'}")
    if not args.json:
        sys.stdout.write(text)
    return 0
