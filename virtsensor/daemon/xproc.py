"""The cross-process end-to-end figure of ``virtsensor bench``: daemon and driver in separate processes.

The daemon (``virtsensor run``) and a driver exchange frames on python-can's ``udp_multicast`` interface
inside a private network namespace (``unshare -n``, or ``unshare -rn`` without root), so no multicast
traffic reaches the host's network. Every subprocess is started from an argument list, never through a
shell: :func:`measure_e2e_cross_process` runs ``unshare -n <python> -m virtsensor.daemon.xproc ...``,
whose :func:`main` (inside the namespace) brings ``lo`` up for multicast with ``ip`` commands, starts the
daemon, waits for its ``started`` log line, drives the ticks and stops the daemon with SIGTERM.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

__all__ = ["MULTICAST_GROUP", "measure_e2e_cross_process", "main"]

MULTICAST_GROUP = "239.74.163.9"
#: ``ip`` commands that make the namespace's loopback carry the multicast group
_LO_SETUP = (("link", "set", "lo", "up"), ("link", "set", "lo", "multicast", "on"),
             ("route", "add", "224.0.0.0/4", "dev", "lo"))


def _netns_prefix() -> tuple[list[str] | None, str | None]:
    """The ``unshare`` command prefix that makes a private network namespace here, or (None, reason)."""
    if shutil.which("unshare") is None or shutil.which("ip") is None:
        return None, "needs unshare(1) and ip(8) to make a private network namespace"
    tried = []
    for prefix in (["unshare", "-n"], ["unshare", "-rn"]):
        try:
            r = subprocess.run([*prefix, "ip", "link", "set", "lo", "up"], capture_output=True, text=True,
                               timeout=20)
        except (OSError, subprocess.TimeoutExpired) as exc:
            tried.append(f"{' '.join(prefix)}: {exc}")
            continue
        if r.returncode == 0:
            return prefix, None
        tried.append(f"{' '.join(prefix)}: {r.stderr.strip() or r.returncode}")
    return None, "private network namespaces are not permitted here (" + "; ".join(tried) + ")"


def measure_e2e_cross_process(model_path: str | os.PathLike, n_ticks: int,
                              timeout_s: float = 120.0) -> tuple[dict | None, str | None]:
    """Last input frame sent -> SAT_FRONT received, daemon and driver in separate processes on udp_multicast
    inside a private network namespace. Returns (percentiles, None) or (None, reason)."""
    try:
        import msgpack  # noqa: F401 - python-can's udp_multicast needs it
    except ImportError:
        return None, "python-can's udp_multicast interface needs msgpack"
    prefix, reason = _netns_prefix()
    if prefix is None:
        return None, reason
    root = Path(__file__).resolve().parent.parent.parent
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(root), env.get("PYTHONPATH", "")])
    with tempfile.TemporaryDirectory(prefix="vs-bench-") as d:
        out = Path(d) / "xproc.json"
        cmd = [*prefix, sys.executable, "-m", "virtsensor.daemon.xproc", str(Path(model_path).resolve()), str(out),
               str(int(n_ticks)), d]
        # its own process group: the driver and the daemon it starts end with this call however it ends
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=d,
                                start_new_session=True)
        try:
            _, stderr = proc.communicate(timeout=timeout_s)
        except BaseException as exc:  # (the timeout, Ctrl-C, bench's SIGTERM: no orphan, then the files go)
            _end_group(proc)
            if isinstance(exc, subprocess.TimeoutExpired):
                return None, f"the cross-process run did not finish within {timeout_s:.0f} s"
            raise
        logs = {n: (Path(d) / n).read_text()[-500:] for n in ("daemon.log",) if (Path(d) / n).exists()}
        if not out.exists():
            return None, f"the cross-process run failed (rc {proc.returncode}): {stderr[-500:]} {logs}"
        res = json.loads(out.read_text())
        if not res.get("n"):
            return None, f"no SAT_FRONT came back across processes ({res.get('lost')} lost): {logs}"
    return res, None


def _end_group(proc: subprocess.Popen) -> None:
    """SIGTERM to ``proc``'s process group (the driver stops its daemon, then itself), SIGKILL to whatever of the
    group is left after 5 s."""
    with contextlib.suppress(ProcessLookupError):
        os.killpg(proc.pid, signal.SIGTERM)
    with contextlib.suppress(subprocess.TimeoutExpired):
        proc.wait(5.0)
    with contextlib.suppress(ProcessLookupError):
        os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()


def _drive(out_path: Path, n_ticks: int) -> None:
    """Send the ticks' frames on udp_multicast, time last input frame -> SAT_FRONT, write the percentiles."""
    import can

    from virtsensor.canbus.codec import CanMatrix
    from virtsensor.daemon.bench import Inputs, percentiles, timed_response

    sat_id = CanMatrix.load().messages["SAT_FRONT"].frame_id
    inputs = Inputs()
    tx = can.Bus(interface="udp_multicast", channel=MULTICAST_GROUP)
    rx = can.Bus(interface="udp_multicast", channel=MULTICAST_GROUP)
    time.sleep(0.3)
    lat: list[float] = []
    lost = run_lost = 0
    try:
        for k in range(n_ticks):
            batch, sync = inputs.tick(k)
            for m in batch[:-1]:
                tx.send(m)
            time.sleep(0.002)  # let the daemon consume them
            us = timed_response(tx, rx, batch, sync, sat_id)
            if us is not None:
                lat.append(us)
                run_lost = 0
            else:
                lost += 1
                run_lost += 1
                if run_lost >= 5:
                    break
    finally:
        tx.shutdown()
        rx.shutdown()
    res: dict[str, Any] = percentiles(lat) or {}
    res["lost"] = lost
    out_path.write_text(json.dumps(res))


def _wait_started(log_path: Path, proc: subprocess.Popen, timeout_s: float = 30.0) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end and proc.poll() is None:
        if log_path.exists() and '"event":"started"' in log_path.read_text():
            return True
        time.sleep(0.1)
    return False


def main(argv: list[str]) -> int:
    """Inside the namespace: ``MODEL OUT.json N_TICKS WORKDIR``. Loopback up for multicast, daemon started,
    ticks driven, daemon stopped; the daemon's stderr goes to ``WORKDIR/daemon.log``. Returns 0, or 1 when
    the set-up or the daemon failed (the reason on stderr). SIGTERM (bench ending the process group) stops the
    daemon first."""
    from virtsensor.interrupt import sigterm_interrupts

    model, out, n_ticks, work = argv[0], Path(argv[1]), int(argv[2]), Path(argv[3])
    with sigterm_interrupts():  # (bench ends the group with SIGTERM: the daemon is stopped in the finally below)
        return _run_daemon(model, out, n_ticks, work)


def _run_daemon(model: str, out: Path, n_ticks: int, work: Path) -> int:
    """Loopback up, the daemon started (in this process group), ticks driven, daemon stopped (SIGTERM, then SIGKILL
    after 10 s)."""
    from virtsensor.daemon.layout import SYNC_ID

    for args in _LO_SETUP:
        r = subprocess.run(["ip", *args], capture_output=True, text=True, timeout=20)
        if r.returncode != 0:
            print(f"ip {' '.join(args)}: {r.stderr.strip()}", file=sys.stderr)
            return 1
    log_path = work / "daemon.log"
    with open(log_path, "w") as log_file:
        daemon = subprocess.Popen([sys.executable, "-m", "virtsensor.cli", "run", "--model", model, "--interface",
                                   "udp_multicast", "--channel", MULTICAST_GROUP, "--sync-id", f"0x{SYNC_ID:X}",
                                   "--log-level", "info"], stdout=subprocess.DEVNULL, stderr=log_file, cwd=work)
        try:
            if not _wait_started(log_path, daemon):
                print("the daemon did not start", file=sys.stderr)
                return 1
            _drive(out, n_ticks)
        finally:
            if daemon.poll() is None:
                daemon.send_signal(signal.SIGTERM)
            try:
                rc = daemon.wait(10)
            except subprocess.TimeoutExpired:
                daemon.kill()
                rc = daemon.wait()
    return 0 if rc == 0 else 1


if __name__ == "__main__":
    if len(sys.argv) != 5:
        print("usage: python -m virtsensor.daemon.xproc MODEL OUT.json N_TICKS WORKDIR (run by virtsensor bench)",
              file=sys.stderr)
        sys.exit(2)
    sys.exit(main(sys.argv[1:]))
