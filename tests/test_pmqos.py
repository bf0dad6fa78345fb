"""The PM QoS CPU-latency request (``virtsensor run --cpu-latency-us``): held while the daemon runs, withdrawn at
stop; refused with a reason where the device cannot be written (not Linux, not permitted)."""

from __future__ import annotations

import os

import pytest

from virtsensor.daemon import pmqos
from virtsensor.daemon.config import load_config
from virtsensor.errors import UserError


def _writable() -> bool:
    return os.path.exists(pmqos.DEVICE) and os.access(pmqos.DEVICE, os.W_OK) and pmqos.current_limit_us() is not None


needs_device = pytest.mark.skipif(not _writable(), reason=f"{pmqos.DEVICE} is not readable and writable here")


@needs_device
def test_request_is_in_force_while_held_and_withdrawn_after():
    # (the kernel's bound is the strictest of every process's requests: another test or bench running beside
    # this one may hold its own, so the bound is checked as "at most ours", and withdrawal as the device closed)
    req = pmqos.CpuLatencyRequest(7)
    assert req.acquire() and req.held and req.error is None
    fd = req._fd
    assert req.acquire() and req._fd == fd  # idempotent: still one request
    assert pmqos.current_limit_us() <= 7
    req.release()
    req.release()
    assert not req.held
    with pytest.raises(OSError):
        os.fstat(fd)  # closed: the kernel has withdrawn the request


def test_refused_request_says_why(monkeypatch):
    monkeypatch.setattr(pmqos, "DEVICE", "/nonexistent/cpu_dma_latency")
    req = pmqos.CpuLatencyRequest(0)
    assert not req.acquire() and not req.held
    assert req.error.startswith("/nonexistent/cpu_dma_latency")
    req.release()  # nothing to release


@pytest.mark.parametrize("bad", [-1, 2**31, 1.5, True, "0"])
def test_bound_is_checked(bad):
    with pytest.raises(ValueError):
        pmqos.CpuLatencyRequest(bad)


def test_config_key_is_checked(tmp_path):
    f = tmp_path / "c.toml"
    f.write_text('interface = "virtual"\nchannel = "x"\ncpu_latency_us = 0\n')
    assert load_config(f).cpu_latency_us == 0
    f.write_text('interface = "virtual"\nchannel = "x"\ncpu_latency_us = -5\n')
    with pytest.raises(UserError, match="cpu_latency_us must be in 0..2000000000"):
        load_config(f)


@needs_device
def test_daemon_holds_the_request_from_start_to_stop():
    import uuid

    import can

    from virtsensor import assets
    from virtsensor.canbus.codec import CanMatrix
    from virtsensor.daemon import VirtualSensor
    from virtsensor.model.onnx import OnnxModel

    bus = can.Bus(interface="virtual", channel=f"pmqos-{uuid.uuid4().hex[:8]}")
    vs = VirtualSensor(bus, OnnxModel.load(assets.model_path()), CanMatrix.load(), cpu_latency_us=0)
    assert vs.cpu_latency.us == 0 and not vs.cpu_latency.held  # asked for at start, not at construction
    vs.start()
    try:
        assert vs.cpu_latency.held and pmqos.current_limit_us() == 0
    finally:
        vs.stop()
    assert not vs.cpu_latency.held


def test_cli_refuses_a_negative_bound(capsys):
    from virtsensor import cli

    rc = cli.main(["run", "--interface", "virtual", "--channel", "x", "--cpu-latency-us", "-1"])
    err = capsys.readouterr().err
    assert rc == 2 and len(err.strip().splitlines()) == 1 and "--cpu-latency-us" in err, err
