"""The daemon and the replayer as separate processes.

* ``udp_multicast`` (python-can) inside a private network namespace the test makes itself
  (``unshare -n``: loopback up, multicast on, a 224.0.0.0/4 route on lo), so no datagram ever
  leaves this machine's sandbox; skipped with the reason where namespaces are not permitted.
* ``socketcan`` on ``vcan0``: only where the kernel has AF_CAN and vcan0 is up.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import can
import numpy as np
import pytest
from runtime_support import synthetic_streams, train_model

from virtsensor.canbus.codec import CanMatrix
from virtsensor.recordings.canlog import simulated_recording, write_log

ROOT = Path(__file__).resolve().parent.parent
GROUP = "239.74.163.2"
REPLAY_S = 15.0  # a few hundred ticks for the latency figures
MATRIX = CanMatrix.load()
SAT_ID = MATRIX.messages["SAT_FRONT"].frame_id


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    """A tiny model trained on synthetic streams, and a CAN log of another synthetic run."""
    d = tmp_path_factory.mktemp("xproc")
    tables = [simulated_recording(*synthetic_streams(20.0, seed=s)).table for s in (1, 2)]
    train_model(tables, d / "sat.onnx", hidden=(16,), max_iter=300)
    time_s, sig = synthetic_streams(REPLAY_S, seed=0)
    write_log(d / "run.asc", time_s, sig)
    return d


def _env() -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")])
    env["PYTHONUNBUFFERED"] = "1"
    return env


def _netns_prefix() -> list[str]:
    """The unshare command that gives a private network namespace here, or skip with the reason."""
    if shutil.which("unshare") is None or shutil.which("ip") is None:
        pytest.skip("needs unshare(1) and ip(8) to make a private network namespace")
    tried = []
    for prefix in (["unshare", "-n"], ["unshare", "-rn"]):
        r = subprocess.run([*prefix, "ip", "link", "set", "lo", "up"], capture_output=True, text=True, timeout=20)
        if r.returncode == 0:
            return prefix
        tried.append(f"{' '.join(prefix)}: {r.stderr.strip() or r.returncode}")
    pytest.skip("private network namespaces are not permitted here (" + "; ".join(tried) + ")")


def _sat_frames(path: Path) -> list[can.Message]:
    with can.LogReader(path) as reader:
        return [m for m in reader if m.arbitration_id == SAT_ID and not m.is_extended_id]


def _check_outputs(frames: list[can.Message]) -> dict:
    """Decode SAT_FRONT frames with cantools; VALID frames must carry in-range numbers."""
    db = MATRIX.db
    dec = [db.decode_message(SAT_ID, bytes(m.data), decode_choices=False) for m in frames]
    st = np.array([(d["SAT_FL_Status"], d["SAT_FR_Status"]) for d in dec], dtype=int)
    val = np.array([(d["SAT_FL"], d["SAT_FR"]) for d in dec], dtype=float)
    valid = st == 0
    assert (np.abs(val[valid]) <= 300).all()
    assert (val[st >= 2] == -327.68).all()  # INVALID/INIT carry the SNA code (raw -16384)
    return {"frames": len(frames), "both_valid": int(valid.all(axis=1).sum()),
            "statuses": sorted(set(map(int, st.ravel())))}


@pytest.mark.slow
def test_udp_multicast_daemon_and_replay_in_private_netns(setup):
    prefix = _netns_prefix()
    pytest.importorskip("msgpack", reason="python-can's udp_multicast interface needs msgpack (pip install msgpack)")
    d = setup
    py = sys.executable
    script = d / "xproc.sh"
    script.write_text(f"""set -u
set -m  # job control: background jobs keep SIGINT (can.logger stops on it)
cd "{d}"
ip link set lo up
ip link set lo multicast on
ip route add 224.0.0.0/4 dev lo
"{py}" -m virtsensor.cli run --model sat.onnx --interface udp_multicast --channel {GROUP} --log-level info \\
    --cpu 1 --realtime 2> daemon.log &
D=$!
"{py}" -m can.logger -i udp_multicast -c {GROUP} -f out.asc > logger.out 2>&1 &
L=$!
for i in $(seq 1 300); do
    grep -q '"event":"started"' daemon.log && grep -q Connected logger.out && break
    sleep 0.1
done
sleep 0.3
"{py}" -m virtsensor.cli replay run.asc --interface udp_multicast --channel {GROUP} --quiet > replay.out 2>&1
echo "replay_rc=$?"
sleep 0.3
kill -TERM $D
wait $D
echo "daemon_rc=$?"
kill -INT $L
# python-can 4.6's logger can hang on SIGINT with udp_multicast: give it 10 s, then end it
for i in $(seq 1 100); do kill -0 $L 2>/dev/null || break; sleep 0.1; done
if kill -0 $L 2>/dev/null; then echo "logger_stuck=1"; kill -TERM $L; sleep 1; kill -KILL $L 2>/dev/null; fi
wait $L
echo "logger_rc=$?"
""")
    r = subprocess.run([*prefix, "bash", str(script)], capture_output=True, text=True, timeout=180, env=_env())
    logs = {n: (d / n).read_text() if (d / n).exists() else "" for n in ("daemon.log", "logger.out", "replay.out")}
    assert r.returncode == 0, (r.stdout, r.stderr, logs)
    rcs = dict(line.split("=") for line in r.stdout.split() if "_rc=" in line or "_stuck=" in line)
    # the daemon and the replayer are under test; the third-party logger only records (if it had
    # to be ended, the frames it wrote are still checked below)
    assert rcs["replay_rc"] == "0" and rcs["daemon_rc"] == "0", (r.stdout, r.stderr, logs)
    assert rcs["logger_rc"] == "0" or rcs.get("logger_stuck") == "1", (r.stdout, r.stderr, logs)
    events = [json.loads(line) for line in logs["daemon.log"].splitlines()]  # JSON lines only
    down = next(e for e in events if e["event"] == "shutdown")
    out = _check_outputs(_sat_frames(d / "out.asc"))
    # ~15 s of inputs at 20 Hz: nearly every tick while they flow must be VALID
    assert out["frames"] >= 250 and out["both_valid"] >= 0.8 * REPLAY_S * 20, out
    assert down["e2e_error"] == 0 and down["send_errors"] == 0 and down["tick_errors"] == 0
    print(f"\n[h] udp_multicast in a private netns: {out['frames']} SAT_FRONT frames, {out['both_valid']} with both "
          f"wheels VALID; daemon (own process) {down['ticks']} ticks, overruns {down['overruns']}, compute p50 "
          f"{down['compute_p50_us']:.0f} us p99 {down['compute_p99_us']:.0f} us, latency to SAT sent "
          f"p50 {down['latency_p50_us']:.0f} us p99 {down['latency_p99_us']:.0f} us max {down['latency_max_us']:.0f} "
          f"us, wake-up lateness p50 {down['wake_late_p50_us']:.0f} us p99 {down['wake_late_p99_us']:.0f} us; "
          f"SIGTERM -> loop exit {down['signal_to_loop_exit_ms']:.2f} ms")


def _socketcan_reason() -> str | None:
    """Why the socketcan test cannot run here (None: it can)."""
    if not hasattr(socket, "AF_CAN"):
        return "this Python has no socket.AF_CAN"
    try:
        socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW).close()
    except OSError as exc:
        if exc.errno in (errno.EAFNOSUPPORT, errno.EPROTONOSUPPORT):
            return f"this kernel has no SocketCAN (socket(AF_CAN): {exc.strerror})"
        return f"cannot open a CAN_RAW socket: {exc}"
    flags = Path("/sys/class/net/vcan0/flags")
    if not flags.exists() or not int(flags.read_text(), 16) & 0x1:
        return "vcan0 is not up (modprobe vcan; ip link add dev vcan0 type vcan; ip link set up vcan0)"
    return None


def test_socketcan_vcan0(setup):
    reason = _socketcan_reason()
    if reason:
        pytest.skip(reason)
    d = setup
    env = _env()
    daemon = subprocess.Popen([sys.executable, "-m", "virtsensor.cli", "run", "--model", str(d / "sat.onnx"),
                               "--interface", "socketcan", "--channel", "vcan0", "--duration", str(REPLAY_S + 4)],
                              stderr=subprocess.PIPE, text=True, env=env)
    col = can.Bus(interface="socketcan", channel="vcan0")
    got: list[can.Message] = []
    stop = threading.Event()

    def collect():
        while not stop.is_set():
            m = col.recv(0.1)
            if m is not None and m.arbitration_id == SAT_ID:
                got.append(m)

    th = threading.Thread(target=collect, daemon=True)
    th.start()
    try:
        time.sleep(2.0)  # start-up
        rp = subprocess.run([sys.executable, "-m", "virtsensor.cli", "replay", str(d / "run.asc"), "--interface",
                             "socketcan", "--channel", "vcan0", "--quiet"], capture_output=True, text=True, env=env,
                            timeout=REPLAY_S + 30)
        assert rp.returncode == 0, rp.stderr
        rc = daemon.wait(REPLAY_S + 30)
    finally:
        stop.set()
        th.join(2)
        col.shutdown()
        if daemon.poll() is None:
            daemon.kill()
    assert rc == 0, daemon.stderr.read()
    out = _check_outputs(got)
    assert out["both_valid"] >= 0.8 * REPLAY_S * 20, out


@pytest.mark.slow
@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM"])
def test_bench_stopped_alone_leaves_no_daemon_and_no_files(setup, tmp_path, sig):
    """``virtsensor bench`` interrupted alone (a supervisor's SIGINT, ``timeout``'s SIGTERM) killed its cross-process
    driver with SIGKILL, and the daemon that driver had started ran on for good as an orphan; SIGTERM also left its
    files in /tmp. Now bench ends the driver's process group (driver and daemon stop cleanly) and its files."""
    import signal

    _netns_prefix()
    pytest.importorskip("msgpack", reason="python-can's udp_multicast interface needs msgpack (pip install msgpack)")
    model = tmp_path / "mine" / "sat.onnx"  # (a path of its own: its daemon is found by it)
    model.parent.mkdir()
    for f in ("sat.onnx", "sat.card.json"):
        shutil.copy(setup / f, model.parent / f)
    scratch = tmp_path / "tmp"
    scratch.mkdir()

    def daemons() -> list[int]:
        found = []
        for p in Path("/proc").iterdir():
            try:
                cmd = (p / "cmdline").read_bytes() if p.name.isdigit() else b""
                if b"virtsensor.cli\x00run\x00" in cmd and str(model).encode() in cmd:  # (the daemon, not the driver)
                    found.append(int(p.name))
            except OSError:
                continue
        return found

    bench = subprocess.Popen([sys.executable, "-m", "virtsensor.cli", "bench", "--quick", "--model", str(model),
                              "--no-cpu-latency", "--soak-ticks", "200"], env={**_env(), "TMPDIR": str(scratch)},
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 240
        while time.monotonic() < deadline and bench.poll() is None and not daemons():
            time.sleep(0.2)
        assert daemons(), "the cross-process daemon never started"
        time.sleep(1.0)
        bench.send_signal(getattr(signal, sig))  # (to bench alone, not its process group)
        rc = bench.wait(30)
        end = time.monotonic() + 5.0
        while time.monotonic() < end and daemons():
            time.sleep(0.1)
        assert not daemons() and rc == {"SIGINT": 130, "SIGTERM": 143}[sig], (rc, bench.stderr.read()[-500:])
        assert not list(scratch.glob("vs-bench-*"))  # (its temporary directory removed)
    finally:
        if bench.poll() is None:
            bench.kill()
        for pid in daemons():
            os.kill(pid, 9)
