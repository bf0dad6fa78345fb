"""Write the input frames ``virtsensor bench`` replays, ``virtsensor/assets/bench_inputs.npz``.

    python tools/bench_inputs.py

They are the frames of the bench's simulated manoeuvre (``virtsensor.daemon.bench.MANOEUVRE``) in its replayed
window, shipped so that the bench runs on the base install (no simulator); needs the ``train`` extra. Run it again
when the simulator, the CAN matrix or the manoeuvre changes (``tests/test_bench.py`` checks the shipped file
against a fresh simulation).
"""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from virtsensor.assets import BENCH_INPUTS  # noqa: E402
from virtsensor.daemon.bench import MANOEUVRE, save_frames, simulated_frames  # noqa: E402


def main() -> int:
    path = ROOT / "virtsensor" / "assets" / BENCH_INPUTS
    frames = simulated_frames(MANOEUVRE)
    save_frames(frames, path)
    print(f"{len(frames)} frames of {MANOEUVRE} -> {path}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
