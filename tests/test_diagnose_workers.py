"""The diagnosis' re-simulation workers end with the process that started them: killed in the middle of a
batch, it leaves no worker running (a loky worker used to finish its batch, and idle on, as an orphan)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
from proc_support import alive, cpu_s, descendants

pytestmark = pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs /proc to find the workers")

BUSY = textwrap.dedent("""
    import sys, time
    from pathlib import Path
    from virtsensor.diagnose.parallel import run_parallel

    def work(out, i):
        t = time.monotonic()
        while time.monotonic() - t < 60.0:
            pass
        Path(out, f"done{i}").touch()

    run_parallel(work, [(sys.argv[1], 0), (sys.argv[1], 1)], n_jobs=2)
""")


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGTERM], ids=["sigkill", "sigterm"])
def test_killed_in_the_middle_of_a_batch_the_diagnosis_leaves_no_worker(tmp_path, sig):
    proc = subprocess.Popen([sys.executable, "-c", BUSY, str(tmp_path)], start_new_session=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    workers: set[int] = set()
    try:
        deadline = time.monotonic() + 60.0
        while not any(cpu_s(p) > 1.0 for p in descendants(proc.pid)):
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, "the workers did not start within 60 s"
            time.sleep(0.05)
        workers = descendants(proc.pid)
        os.kill(proc.pid, sig)
        proc.wait(timeout=5.0)
        deadline = time.monotonic() + 5.0
        while alive(workers) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not alive(workers), f"workers still running 5 s after the kill: {sorted(alive(workers))}"
        assert not list(tmp_path.iterdir())
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        for p in alive(workers):
            os.kill(p, signal.SIGKILL)
