"""`virtsensor simulate` and `campaign` from the command line: outputs and bad input."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from sim_support import recorded_inputs

from virtsensor.cli import main
from virtsensor.recordings.canlog import read_csv
from virtsensor.signals import INPUTS, OUTPUTS, TABLE_COLUMNS


def run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "virtsensor.cli", *args], capture_output=True, text=True,
                          timeout=300)


def test_simulate_writes_the_canonical_20hz_table(tmp_path):
    out = tmp_path / "pulse.csv"
    assert main(["simulate", "steering-pulse", "--speed", "50", "--mu", "0.7", "--seed", "3",
                 "--out", str(out)]) == 0
    table = read_csv(out)
    assert list(table)[: len(TABLE_COLUMNS)] == list(TABLE_COLUMNS)
    t = table["time_s"]
    assert np.allclose(np.diff(t), 0.05)
    for name in (*INPUTS, *OUTPUTS):
        assert np.all(np.isfinite(table[name])), name
    # the truth that explains the SAT travels with it
    for name in ("alpha_fl_rad", "kappa_fl_1", "fz_fl_n", "fy_fl_n", "fx_fl_n", "fz_fr_n"):
        assert name in table
    assert np.abs(table["sat_fl_nm"]).max() > 5.0
    # (same seed, same data: test_campaign_is_deterministic_whatever_the_number_of_workers)


def test_parameter_overrides_change_the_car(tmp_path):
    light, heavy = tmp_path / "light.csv", tmp_path / "heavy.csv"
    inputs = str(recorded_inputs(tmp_path, 15.0, n=20))  # a short run: any manoeuvre shows the load
    common = ["simulate", "recorded", "--inputs", inputs, "--mu", "1", "--seed", "1"]
    assert main([*common, "--out", str(light)]) == 0
    assert main([*common, "--set", "vehicle.mass_kg=1750", "--out", str(heavy)]) == 0
    a, b = read_csv(light), read_csv(heavy)
    # a heavier car loads its front suspension more at the same path and speed
    assert np.abs(b["fz_fl_n"]).mean() > 1.1 * np.abs(a["fz_fl_n"]).mean()


@pytest.mark.parametrize(
    "args, needle",
    [
        (["simulate", "moonwalk", "--speed", "50", "--mu", "1"], "unknown manoeuvre 'moonwalk'"),
        (["simulate", "fishhook", "--speed", "150", "--mu", "1"], "outside fishhook's range 40-80 km/h"),
        (["simulate", "fishhook", "--speed", "60", "--mu", "3"], "--mu: 3 is out of range"),
        (["simulate", "fishhook", "--speed", "60", "--mu", "1", "--set", "vehicle.mas_kg=3"],
         "unknown parameter 'vehicle.mas_kg' (did you mean vehicle.mass_kg?)"),
        (["simulate", "fishhook", "--speed", "60", "--mu", "1", "--set", "vehicle.mass_kg=heavy"],
         "vehicle.mass_kg: expected float"),
        (["simulate", "fishhook", "--speed", "fast", "--mu", "1"], "--speed: 'fast' is not a number"),
        (["simulate", "fishhook", "--speed", "60", "--mu", "1", "--longitudinal", "torque"],
         "--longitudinal goes with the manoeuvre 'recorded' only"),
    ],
)
def test_bad_input_is_one_line_exit_2_and_no_file(tmp_path, args, needle):
    out = tmp_path / "x.csv"
    res = run_cli(*args, "--out", str(out))
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 or lines[-1].startswith("virtsensor"), res.stderr
    assert needle in res.stderr
    assert "Traceback" not in res.stderr
    assert not out.exists() and list(tmp_path.iterdir()) == []


def test_a_value_out_of_range_from_a_params_file_names_the_file(tmp_path):
    """Its key and value alone sent the user looking through --set and every --params file for it."""
    from sim.params import ParamError, car_parameters

    toml = tmp_path / "car.toml"
    toml.write_text("[vehicle]\nmass_kg = 1\n[steering]\nassist_gains = [1, 1, 1, 1, 1, 99]\n")
    with pytest.raises(ParamError) as e:
        car_parameters([], [toml])
    assert str(e.value) == f"{toml}: car parameter vehicle.mass_kg=1 is outside its physical range [300, 5000] kg"
    with pytest.raises(ParamError) as e:
        car_parameters(["vehicle.mass_kg=1400"], [toml])
    assert str(e.value).startswith(f"{toml}: car parameter steering.assist_gains[5]=99 is outside"), str(e.value)
    with pytest.raises(ParamError, match="^car parameter vehicle.mass_kg=2 "):  # (--set names key and value itself)
        car_parameters(["vehicle.mass_kg=2", "steering.assist_gains=[1, 1, 1, 1, 1, 1]"], [toml])


@pytest.mark.parametrize(("assignment", "needle"), [
    ("vehicle.mass_kg=-5", "vehicle.mass_kg=-5 is outside its physical range [300, 5000] kg"),
    ("vehicle.mass_kg=0", "vehicle.mass_kg=0 is outside its physical range [300, 5000] kg"),
    ("vehicle.mass_kg=1e9", "vehicle.mass_kg=1e+09 is outside its physical range [300, 5000] kg"),
    ("vehicle.mass_kg=1", "vehicle.mass_kg=1 is outside its physical range [300, 5000] kg"),
    ("steering.ratio=0", "steering.ratio=0 is outside its physical range [5, 40]"),
    ("simulation.step_s=0", "simulation.step_s=0 is outside its physical range (0, 0.01] s"),
    ("simulation.step_s=-1", "simulation.step_s=-1 is outside its physical range (0, 0.01] s"),
    ("simulation.step_s=0.003", "simulation.step_s=0.003 must divide the driver's 0.01 s update period"),
    ("simulation.record_rate_hz=0", "simulation.record_rate_hz=0 is outside its physical range [20, 100] Hz"),
    ("simulation.record_rate_hz=50", "record_rate_hz=50 must divide the driver's 100 Hz (100, 50, 25 or 20 Hz) and "
                                     "be at least the fastest sensor's rate (100 Hz)"),
    ("vehicle.front_axle_load_fraction=2", "front_axle_load_fraction=2 is outside its physical range (0, 1)"),
    ("simulation.gravity_mps2=0", "gravity_mps2=0 is outside its physical range [9.5, 10.1] m/s^2"),
    ("steering.assist_gains=[1]", "assist_gains=[1.0]: expected one gain per speed of steering.assist_speeds_mps"),
    ("steering.assist_speeds_mps=[0,8,8,22,30,45]", "breakpoints must increase strictly (entry 2, 8, is not above 8"),
    ("tyres.pressure_left_right_front_pa=4e5", "puts the front right tyre at 20000 Pa, outside its physical range"),
])
def test_car_parameters_outside_their_physical_range_are_refused(assignment, needle):
    from sim.params import ParamError, car_parameters

    with pytest.raises(ParamError, match="^car parameter ") as e:
        car_parameters([assignment])
    assert needle in str(e.value) and "\n" not in str(e.value)


def test_the_cars_the_project_uses_pass_the_parameter_check():
    from sim.effects import CAUSES, EFFECTS, with_effect
    from sim.params import car_parameters, check_car

    base = car_parameters(["vehicle.mass_kg=1650", "steering.assist_damping_nmsprad=4", "tyres.relaxation_scale=0.2",
                           "brakes.front_share=0.2", "steering.max_road_wheel_angle_rad=0.1",
                           "simulation.step_s=0.0025", "vehicle.mass_kg=300"])
    for cause in CAUSES:  # the diagnosis' search bounds on the default car
        for value in EFFECTS[cause].bounds:
            if np.isfinite(value):
                check_car(with_effect(car_parameters(), cause, value, "ay_mps2"))
    check_car(base)


def test_a_bad_car_writes_nothing_and_keeps_an_earlier_output(tmp_path, capsys):
    out = tmp_path / "x.csv"
    out.write_text("earlier run\n")
    argv = ["simulate", "steering-pulse", "--speed", "50", "--mu", "1", "--set", "vehicle.mass_kg=1", "--out", str(out)]
    assert main(argv) == 2
    assert out.read_text() == "earlier run\n" and sorted(p.name for p in tmp_path.iterdir()) == ["x.csv"]
    assert main(["campaign", "tiny", "--out", str(tmp_path / "c"), "--set", "simulation.step_s=0"]) == 2
    assert not (tmp_path / "c").exists()
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and "vehicle.mass_kg=1 " in err[0] and "simulation.step_s=0 " in err[1], err


@pytest.mark.parametrize(("backend", "extra"), [("ray", "distributed"), ("dask", "dask")])
def test_a_cluster_backend_without_its_extra_names_it_in_one_line(tmp_path, capsys, monkeypatch, backend, extra):
    for module in ("ray", "dask", "distributed"):
        monkeypatch.setitem(sys.modules, module, None)  # as if not installed
    out = tmp_path / "c"
    assert main(["campaign", "tiny", "--out", str(out), "--backend", backend, "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].endswith(f"--backend {backend} needs the optional extra '{extra}' (missing: "
                                             f"{backend}{', distributed' if backend == 'dask' else ''}): "
                                             f"pip install 'virtsensor[{extra}]'"), err
    assert not out.exists()


@pytest.mark.slow
@pytest.mark.parametrize(("backend", "module"), [("ray", "ray"), ("dask", "distributed")])
def test_a_campaign_on_a_local_cluster_writes_the_runs_loky_writes(tmp_path, backend, module):
    pytest.importorskip(module, reason=f"the optional extra of --backend {backend}")
    a, b = tmp_path / "a", tmp_path / "b"
    assert main(["campaign", "tiny", "--out", str(a), "--seed", "4", "--quiet", "--jobs", "2"]) == 0
    assert main(["campaign", "tiny", "--out", str(b), "--seed", "4", "--quiet", "--jobs", "2",
                 "--backend", backend]) == 0
    runs = sorted(p.name for p in a.iterdir() if p.suffix == ".csv")
    assert runs and runs == sorted(p.name for p in b.iterdir() if p.suffix == ".csv")
    for name in runs:
        assert (a / name).read_bytes() == (b / name).read_bytes(), name


def test_malformed_tir_is_named(tmp_path):
    bad = tmp_path / "bad.tir"
    bad.write_text("[MODEL]\nFITTYP = 61\n[VERTICAL]\nFNOMIN = four thousand\n")
    out = tmp_path / "x.csv"
    res = run_cli("simulate", "fishhook", "--speed", "60", "--mu", "1", "--set", f"tyres.file={bad}", "--out", str(out))
    assert res.returncode == 2
    assert "bad.tir" in res.stderr and "Traceback" not in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1
    assert not out.exists()


@pytest.mark.slow
def test_campaign_is_deterministic_whatever_the_number_of_workers(tmp_path, capsys):
    a, b = tmp_path / "a", tmp_path / "b"
    assert main(["campaign", "tiny", "--out", str(a), "--seed", "4", "--quiet", "--jobs", "1"]) == 0
    assert "tiny: 4 runs (all completed), " in capsys.readouterr().err
    runs = {e["manoeuvre"]: e["outcome"] for e in json.loads((a / "manifest.json").read_text())["runs"]}
    dlc = runs.pop("double-lane-change")  # a planned path: through the exit gate, 155 m
    assert dlc["status"] == "completed" and dlc["planned_m"] == 155.0 < dlc["driven_m"]
    assert all("driven_m" not in o for o in runs.values())  # open-loop runs are planned by time only
    assert main(["campaign", "tiny", "--out", str(b), "--seed", "4", "--quiet", "--jobs", "2",
                 "--batch-size", "2"]) == 0
    files = sorted(p.name for p in a.iterdir())
    assert "manifest.json" in files and ".campaign.json" in files and len(files) == 6
    for name in files:
        if name != "manifest.json":
            assert (a / name).read_bytes() == (b / name).read_bytes(), name
    # refuses to write into a directory that already holds a campaign
    res = run_cli("campaign", "tiny", "--out", str(a), "--quiet")
    assert res.returncode == 2 and "not empty" in res.stderr


@pytest.mark.slow
def test_a_recorded_run_is_resimulated_from_its_driver_inputs(tmp_path):
    """Drive the simulator with the steering-wheel angle and speed of a recording:
    the same car on the same road gives back the same SATs."""
    rec = tmp_path / "rec.csv"
    assert main(["simulate", "single-sine", "--speed", "60", "--mu", "1", "--seed", "2", "--out", str(rec)]) == 0
    again = tmp_path / "again.csv"
    assert main(["simulate", "recorded", "--inputs", str(rec), "--mu", "1", "--out", str(again)]) == 0
    a, b = read_csv(rec), read_csv(again)
    n = min(len(a["time_s"]), len(b["time_s"]))
    for w in ("sat_fl_nm", "sat_fr_nm"):
        err = np.abs(a[w][:n] - b[w][:n])
        assert np.mean(err) < 0.1 * np.std(a[w][:n]), (w, np.mean(err), np.std(a[w][:n]))
    # a different road under the same inputs: the SATs change (the re-simulation is real)
    wet = tmp_path / "wet.csv"
    assert main(["simulate", "recorded", "--inputs", str(rec), "--mu", "0.4", "--out", str(wet)]) == 0
    c = read_csv(wet)
    assert np.abs(c["sat_fl_nm"][:n]).max() < 0.8 * np.abs(a["sat_fl_nm"][:n]).max()
    # the recorded inputs must be there
    res = run_cli("simulate", "recorded", "--mu", "1", "--out", str(tmp_path / "x.csv"))
    assert res.returncode == 2 and "--inputs" in res.stderr


def test_recorded_inputs_that_never_move_the_car_write_nothing(tmp_path, capsys):
    """(It wrote a 1-row table, 'STOPPED', exit 0: a table train and score refuse.)"""
    inputs = recorded_inputs(tmp_path, 0.0)
    out = tmp_path / "rec.csv"
    assert main(["simulate", "recorded", "--mu", "1", "--inputs", str(inputs), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "STOPPED after 1 sample(s)" in err and "never move" in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["inputs.csv"]


def test_a_run_that_stops_after_a_usable_stretch_is_written_and_says_so(tmp_path, capsys):
    """The car stops halfway (the recorded speed drops to 0): the run up to there is kept, cut short, exit 0."""
    inputs = recorded_inputs(tmp_path, np.where(np.arange(80) < 40, 15.0, 0.0))
    out = tmp_path / "rec.csv"
    assert main(["simulate", "recorded", "--mu", "1", "--inputs", str(inputs), "--out", str(out)]) == 0
    assert "STOPPED at t=" in capsys.readouterr().err
    assert 20 < len(read_csv(out)["time_s"]) < 80


def test_a_run_never_takes_over_another_recordings_metadata(tmp_path, capsys):
    """``x.blf`` beside ``x.csv`` would share ``x.json``: refused in one line, exit 2, the csv's metadata kept;
    writing ``x.csv`` again (its own metadata) is allowed. (Short recorded runs: the manoeuvre does not matter.)"""
    csv, blf, meta = tmp_path / "x.csv", tmp_path / "x.blf", tmp_path / "x.json"
    inputs = str(recorded_inputs(tmp_path, 15.0, n=20))

    def simulate(mu: str, out) -> int:
        return main(["simulate", "recorded", "--mu", mu, "--inputs", inputs, "--out", str(out)])

    assert simulate("0.7", csv) == 0
    before = meta.read_bytes()
    capsys.readouterr()
    assert simulate("0.5", blf) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "metadata of another recording, x.csv" in err[0], err
    assert meta.read_bytes() == before and not blf.exists()
    assert simulate("0.5", csv) == 0
    assert json.loads(meta.read_text())["file"].endswith("x.csv") and meta.read_bytes() != before
    (tmp_path / "sub").mkdir()
    for other, mu in (("", "0.6"), (".", "0.8"), ("sub", "0.9")):  # (metadata naming no recording: nothing to protect)
        meta.write_text(json.dumps({"file": other}))
        assert simulate(mu, blf) == 0
        blf.unlink()


# ------------------------------------------------------------------ a simulation that diverges (last line of defence)
#: Vehicle.derivatives made to overflow in the runs on a road of friction 1.0 (the tiny campaign's steering pulse):
#: a car that passed every check but that the integration cannot take
_OVERFLOW_AT_MU_1 = """
def _overflowing(derivatives):
    def overflowing(self, x, u):
        import numpy as np

        k, aux = derivatives(self, x, u)
        factor = np.where(np.asarray(u.mu) == 1.0, 1e300, 1.0)[:, None]
        return k * factor * factor, aux
    return overflowing
"""


def _overflow_at_mu_1(monkeypatch):
    from sim.vehicle import Vehicle

    scope: dict = {}
    exec(_OVERFLOW_AT_MU_1, scope)
    monkeypatch.setattr(Vehicle, "derivatives", scope["_overflowing"](Vehicle.derivatives))


def test_a_simulation_that_diverges_is_one_line_naming_the_run(tmp_path, capsys, monkeypatch):
    """It was a FloatingPointError traceback after a screen of RuntimeWarnings (exit 1)."""
    import warnings

    _overflow_at_mu_1(monkeypatch)
    out = tmp_path / "x.csv"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert main(["simulate", "double-lane-change", "--speed", "80", "--mu", "1", "--out", str(out)]) == 2
    assert not [w for w in caught if issubclass(w.category, RuntimeWarning)], [str(w.message) for w in caught]
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["virtsensor simulate: error: the simulation diverged (its state became non-finite) at t=0.00 s in "
                   "double-lane-change at 80 km/h, mu 1, seed 0: the car's parameters or tyre coefficients (--set, "
                   "--params, --tyre) hold a value it cannot be simulated with"], err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
def test_a_campaign_whose_worker_diverges_is_one_line_and_leaves_nothing(tmp_path):
    """The divergence happens in a loky worker (one batch per run, two workers) while the other runs are written;
    joblib re-raises it in the campaign's process, which removes what was written and says which run. Injected
    at the workers' start (sitecustomize), as nothing else reaches into a worker."""
    import os
    from pathlib import Path

    site = tmp_path / "site"
    site.mkdir()
    (site / "sitecustomize.py").write_text(
        "import os\n" + _OVERFLOW_AT_MU_1 +
        "if os.environ.setdefault('VS_TEST_CAMPAIGN_PID', str(os.getpid())) != str(os.getpid()):  # a worker\n"
        "    import sim.vehicle\n"
        "    sim.vehicle.Vehicle.derivatives = _overflowing(sim.vehicle.Vehicle.derivatives)\n")
    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(site), str(root), os.environ.get("PYTHONPATH", "")])}
    env.pop("VS_TEST_CAMPAIGN_PID", None)
    out = tmp_path / "camp"
    res = subprocess.run([sys.executable, "-m", "virtsensor.cli", "campaign", "tiny", "--out", str(out), "--jobs",
                          "2", "--batch-size", "1", "--quiet"], capture_output=True, text=True, timeout=300, env=env)
    assert res.returncode == 2, res.stderr
    err = res.stderr.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("virtsensor campaign: error: the simulation diverged (its state "
                                               "became non-finite) at t=0.00 s in steering-pulse at 50 km/h, mu 1, "
                                               "seed "), res.stderr
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["site"]
    # the same run in the campaign's own process is not made to diverge: it was the worker's divergence
    pulse = tmp_path / "pulse.csv"
    ok = subprocess.run([sys.executable, "-m", "virtsensor.cli", "simulate", "steering-pulse", "--speed", "50",
                         "--mu", "1", "--out", str(pulse)], capture_output=True, text=True, timeout=300, env=env)
    assert ok.returncode == 0 and pulse.exists(), ok.stderr


def test_floating_point_errors_of_a_run_that_goes_on_are_warned_once(monkeypatch):
    """The engine keeps numpy's floating-point errors of each step until it knows whether the step diverged;
    those of a run that goes on are still warned, once per kind, naming the batch's runs."""
    import warnings

    import numpy as np

    from sim.api import simulate
    from sim.vehicle import Vehicle

    derivatives = Vehicle.derivatives

    def with_a_division_by_zero(self, x, u):
        np.divide(np.ones(1), np.zeros(1))  # (the result is not used)
        return derivatives(self, x, u)

    monkeypatch.setattr(Vehicle, "derivatives", with_a_division_by_zero)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        run = simulate("steering-pulse", 50.0, 1.0, seed=1)
    assert run.outcome["status"] == "completed"
    messages = [str(w.message) for w in caught if issubclass(w.category, RuntimeWarning)]
    assert messages == ["floating-point divide by zero in the simulation at t=0.00 s (batch of steering-pulse at "
                        "50 km/h, mu 1, seed 1)"], messages
