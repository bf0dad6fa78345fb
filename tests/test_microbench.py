"""tools/microbench.py: the figures behind the README's micro-benchmark rows are produced."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("microbench", ROOT / "tools" / "microbench.py")
microbench = importlib.util.module_from_spec(_spec)
sys.modules["microbench"] = microbench
_spec.loader.exec_module(microbench)


def test_every_figure_is_measured_and_written(tmp_path, capsys):
    out = tmp_path / "micro.json"
    assert microbench.main(["--repeats", "1", "--json", str(out)]) == 0
    res = json.loads(out.read_text())
    assert 0 < res["tyre_call_150x4_ms"] < 1000
    assert 0 < res["can_frame"]["encode_us"] < 10_000 and 0 < res["can_frame"]["decode_us"] < 10_000
    assert set(res["onnx_rows_per_s_46885"]) == {"paper", "improved"}
    assert all(v > 1000 for v in res["onnx_rows_per_s_46885"].values())
    assert "paper_fit_s" not in res  # only with --data
    assert "M rows/s (paper)" in capsys.readouterr().out


def test_bad_command_line_is_one_line_and_exit_2(tmp_path, capsys):
    assert microbench.main(["--repeats", "0"]) == 2
    assert microbench.main(["--data", str(tmp_path / "none")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["microbench: --repeats must be >= 1", f"microbench: --data {tmp_path / 'none'}: no such directory"]
