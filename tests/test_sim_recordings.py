"""A simulated run as a CAN log: written through python-can, read back, same table."""

from __future__ import annotations

import numpy as np
import pytest

from sim.api import simulate
from sim.params import car_parameters
from virtsensor import signals as cat
from virtsensor.recordings.canlog import read_csv, read_log
from virtsensor.recordings.simulated import write_run


@pytest.fixture(scope="module")
def recordings(tmp_path_factory):
    """One simulated run, written as a table and as each CAN log format (simulated once)."""
    d = tmp_path_factory.mktemp("rec")
    paths = {suffix: d / f"dlc{suffix}" for suffix in (".csv", ".blf", ".asc", ".log")}
    sim_run = simulate("double-lane-change", 70.0, 0.7, 5, car_parameters())
    for path in paths.values():
        write_run(sim_run, path)
    return paths


@pytest.mark.parametrize("suffix", [".blf", ".asc", ".log"])
def test_log_read_back_equals_the_csv_table(recordings, suffix):
    table = read_csv(recordings[".csv"])
    rec = read_log(recordings[suffix])
    assert rec.e2e_errors == 0 and rec.unknown_frames == 0
    back = rec.table
    n = min(len(table["time_s"]), len(back["time_s"]))
    assert n > 150 and abs(len(table["time_s"]) - len(back["time_s"])) <= 1
    assert np.allclose(table["time_s"][:n], back["time_s"][:n], atol=1e-6)
    for name in (*cat.INPUTS, *cat.OUTPUTS):
        res = cat.SIGNALS[name].resolution
        err = np.abs(table[name][:n] - back[name][:n]).max()
        assert err <= 0.5 * res + 1e-9, (name, err, res)


def test_the_table_carries_what_the_sensors_measured(recordings):
    """The inputs differ from the truth by the sensors' noise, latency and CAN
    quantisation only: strongly correlated, never identical."""
    table = read_csv(recordings[".csv"])
    ay = table["ay_mps2"]
    assert np.std(ay) > 1.0
    # the front SAT reference is the wheel-force transducer: quantised to its resolution
    q = table["sat_fl_nm"] / cat.SIGNALS["sat_fl_nm"].resolution
    assert np.allclose(q, np.round(q), atol=1e-6)
    # in a left-hand part of the lane change, yaw rate and SAT have opposite signs (ISO 8855)
    left = table["yaw_rate_radps"] > 0.15
    assert left.sum() > 5 and np.all(table["sat_fl_nm"][left] + table["sat_fr_nm"][left] < 0)


def test_can_logger_tools_read_our_log(recordings):
    """Interoperability with python-can's reader and cantools' own DBC decoding."""
    import can
    import cantools

    db = cantools.database.load_file(str(_dbc()))
    n = 0
    with can.LogReader(str(recordings[".blf"])) as reader:
        for msg in reader:
            decoded = db.decode_message(msg.arbitration_id, bytes(msg.data))
            assert decoded
            n += 1
    assert n > 1000


def _dbc():
    from pathlib import Path

    return Path(__file__).resolve().parents[1] / "dbc" / "virtsensor.dbc"
