"""`virtsensor tyre`: the figures of the bundled MF 6.1 files, and the refusal of broken property files."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from sim.tir import bundled_tir
from virtsensor.cli import main
from virtsensor.errors import UserError

MF61 = "mf61_255_55R20.tir"  # Simscape Vehicle Templates' copy
MFEVAL = "mf61_mfeval_255_55R20.tir"  # MFeval's own example

#: Mz peaks at FNOMIN, nominal pressure, zero camber, from an independent port of MFeval's solver:
#: file -> {LMUY: (Mz max Nm, alpha deg, Mz min Nm, alpha deg)}, and Mz max at +10 % pressure
MZ_PEAKS = {
    MF61: {1.0: (132.7, 2.12, -116.8, -2.41), 0.7: (94.4, 1.48, -80.4, -1.70)},
    MFEVAL: {1.0: (117.5, 2.31, -129.3, -2.64), 0.7: (81.9, 1.58, -90.9, -1.88)},
}
MZ_MAX_HIGH_PRESSURE = {MF61: 118.7, MFEVAL: 103.4}


def _figures(capsys: pytest.CaptureFixture[str], *args: str) -> dict:
    assert main(["tyre", *args, "--json", "-"]) == 0
    return json.loads(capsys.readouterr().out)


def _at(figures: dict, load: float = 1.0, pressure: float = 1.0) -> dict:
    return next(c for c in figures["conditions"] if c["load_factor"] == load and c["pressure_factor"] == pressure)


@pytest.mark.parametrize("name", [MF61, MFEVAL])
@pytest.mark.parametrize("lmuy", [1.0, 0.7])
def test_mz_peaks_of_the_bundled_files(capsys: pytest.CaptureFixture[str], name: str, lmuy: float) -> None:
    figures = _figures(capsys, name.removesuffix(".tir"), "--set", f"LMUY={lmuy}")
    nominal = _at(figures)
    mz_max, a_max, mz_min, a_min = MZ_PEAKS[name][lmuy]
    assert nominal["mz_max_nm"] == pytest.approx(mz_max, abs=0.1)
    assert nominal["mz_max_alpha_deg"] == pytest.approx(a_max, abs=0.05)
    assert nominal["mz_min_nm"] == pytest.approx(mz_min, abs=0.1)
    assert nominal["mz_min_alpha_deg"] == pytest.approx(a_min, abs=0.05)
    if lmuy == 1.0:
        assert _at(figures, pressure=1.1)["mz_max_nm"] == pytest.approx(MZ_MAX_HIGH_PRESSURE[name], abs=0.1)
        assert figures["defaults"] == {"LMUV": 0.0}


def test_report_table_and_its_figures(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["tyre", str(bundled_tir(MFEVAL))]) == 0
    text = capsys.readouterr().out
    for row in ("cornering stiffness", "Fy peak", "Mz peak, alpha > 0", "Mz peak, alpha < 0",
                "pneumatic trail at zero slip", "longitudinal slip stiffness", "inflation pressure -10 % / +10 %"):
        assert row in text, row
    assert "117.5" in text and "-129.3" in text
    figures = _figures(capsys, str(bundled_tir(MFEVAL)))
    assert len(figures["conditions"]) == 9
    nominal = _at(figures)
    assert nominal["cornering_stiffness_n_per_rad"] < 0.0  # ISO-W: alpha > 0 gives Fy < 0
    assert abs(nominal["fy_peak_n"]) > 0.9 * figures["fnomin_n"]
    assert 3.0 < abs(nominal["fy_peak_alpha_deg"]) < 12.0
    assert 0.02 < nominal["trail_at_zero_slip_m"] < 0.06
    assert nominal["slip_stiffness_n"] > 1e5
    loads = [_at(figures, load)["cornering_stiffness_n_per_rad"] for load in (0.5, 1.0, 1.5)]
    assert loads[0] > loads[1] > loads[2]  # more load, stiffer (more negative)


def _broken(tmp_path: Path, edit: str, key: str = "PKY1") -> tuple[Path, int]:
    """The MFeval file with its ``key`` line removed (edit ''), or replaced by ``edit``; -> (path, 1-based line)."""
    lines = bundled_tir(MFEVAL).read_text().splitlines()
    i = next(i for i, ln in enumerate(lines) if ln.split("=")[0].strip() == key)
    if edit:
        lines[i] = edit
    else:
        del lines[i]
    path = tmp_path / "broken.tir"
    path.write_text("\n".join(lines) + "\n")
    return path, i + 1


def _refused(capsys: pytest.CaptureFixture[str], path: Path, *extra: str) -> str:
    assert main(["tyre", str(path), *extra]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1, captured.err
    return lines[0]


def test_missing_pky1_is_refused_with_file_key_and_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path, _ = _broken(tmp_path, "")
    section = 1 + bundled_tir(MFEVAL).read_text().splitlines().index("[LATERAL_COEFFICIENTS]")
    msg = _refused(capsys, path)
    assert f"{path}:{section}: missing coefficient PKY1 in [LATERAL_COEFFICIENTS]" in msg, msg


@pytest.mark.parametrize(("key", "edit", "expected"), [
    ("FITTYP", "FITTYP = 52", "FITTYP = 52.0: only Magic Formula 6.1/6.2"),
    ("PKY1", "PKY1 = abc", "cannot parse the value of PKY1"),
    ("PKY1", "PKY1 = 'abc'", "PKY1"),
    ("PKY1", "PKY1 = nan", "PKY1"),
    ("LENGTH", "LENGTH = 'mm'", "unit LENGTH is not supported"),
])
def test_bad_value_is_refused_with_file_key_and_line(tmp_path: Path, capsys: pytest.CaptureFixture[str], key: str,
                                                     edit: str, expected: str) -> None:
    path, line = _broken(tmp_path, edit, key)
    msg = _refused(capsys, path, "--json", str(tmp_path / "f.json"))
    assert f"{path}:{line}: " in msg and expected in msg, msg
    assert not (tmp_path / "f.json").exists()


@pytest.mark.parametrize(("key", "edit", "expected"), [
    ("FNOMIN", "FNOMIN = 6.752", "FNOMIN = 6.752 N: a nominal load below the 1000 to 25000 N of a passenger-car or "
                                 "light-truck tyre; is it in kN?"),
    ("UNLOADED_RADIUS", "UNLOADED_RADIUS = 394.3", "UNLOADED_RADIUS = 394.3 m: a free radius above the 0.2 to 0.6 m "
                                                   "of a passenger-car or light-truck tyre; is it in mm?"),
    ("WIDTH", "WIDTH = 255", "WIDTH = 255 m: a section width above the 0.08 to 0.45 m of a passenger-car or "
                             "light-truck tyre; is it in mm?"),
    ("NOMPRES", "NOMPRES = 2.6", "NOMPRES = 2.6 Pa: an inflation pressure below the 100000 to 650000 Pa of a "
                                 "passenger-car or light-truck tyre; is it in bar?"),
    ("INFLPRES", "INFLPRES = 260", "INFLPRES = 260 Pa: an inflation pressure below the 100000 to 650000 Pa of a "
                                   "passenger-car or light-truck tyre; is it in kPa?"),
    ("LONGVL", "LONGVL = 60", "LONGVL = 60 m/s: a reference speed above the 1 to 40 m/s of a passenger-car or "
                              "light-truck tyre; is it in km/h?"),
    ("VERTICAL_STIFFNESS", "VERTICAL_STIFFNESS = 314.9", "VERTICAL_STIFFNESS = 314.9 N/m: a vertical stiffness "
                                                         "below the 50000 to 1.5e+06 N/m of a passenger-car or "
                                                         "light-truck tyre; is it in N/mm (kN/m)?"),
])
def test_a_value_in_the_wrong_unit_is_refused_with_file_key_line_and_likely_unit(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], key: str, edit: str, expected: str) -> None:
    """A .tir whose [UNITS] say SI but whose load, size, pressure, speed or stiffness is in another unit: a
    nominal load of 6.752 N made the simulation diverge at t = 0 (a traceback) and 'virtsensor tyre' print it."""
    path, line = _broken(tmp_path, edit, key)
    assert _refused(capsys, path, "--json", str(tmp_path / "f.json")) == f"virtsensor tyre: error: {path}:{line}: " \
                                                                         f"{expected}"
    assert not (tmp_path / "f.json").exists()


def test_a_value_in_the_wrong_unit_stops_simulate_and_campaign_before_any_work(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The reviewer's case: FNOMIN in kN. simulate (with --tyre or --set tyres.file) and campaign refuse it in one
    line naming file, key and line; no run file, no campaign directory."""
    path, line = _broken(tmp_path, "FNOMIN = 6.752", "FNOMIN")
    out, camp = tmp_path / "dlc.csv", tmp_path / "camp"
    dlc = ["simulate", "double-lane-change", "--speed", "80", "--mu", "1", "--out", str(out)]
    for argv in ([*dlc, "--tyre", str(path)], [*dlc, "--set", f"tyres.file={path}"],
                 ["campaign", "tiny", "--tyre", str(path), "--out", str(camp), "--quiet"]):
        assert main(argv) == 2, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and f"{path}:{line}: FNOMIN = 6.752 N: a nominal load below" in err[0], err
        assert err[0].endswith("is it in kN?"), err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["broken.tir"]


def test_set_is_checked_as_the_file_is(capsys: pytest.CaptureFixture[str]) -> None:
    """--set FNOMIN=1e308 printed RuntimeWarnings and null figures (exit 0)."""
    assert main(["tyre", MF61, "--set", "FNOMIN=1e308", "--json", "-"]) == 2
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err.strip() == (
        f"virtsensor tyre: error: {bundled_tir(MF61)} with --set FNOMIN: FNOMIN = 1e+308 N: a nominal load above the "
        "1000 to 25000 N of a passenger-car or light-truck tyre; is it in another unit?")


def _no_runtime_warning(argv: list[str]) -> int:
    """main(argv), asserting numpy warned nothing (pytest would keep a warning off the captured stderr)."""
    import warnings

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rc = main(argv)
    assert not [w for w in caught if issubclass(w.category, RuntimeWarning)], [str(w.message) for w in caught]
    return rc


def test_a_coefficient_that_overflows_the_magic_formula_is_named(capsys: pytest.CaptureFixture[str]) -> None:
    """--set PKY1=1e308 gave RuntimeWarnings and null figures (exit 0): now one line naming the coefficient."""
    assert _no_runtime_warning(["tyre", MF61, "--set", "PKY1=1e308", "--json", "-"]) == 2
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err.strip() == (
        f"virtsensor tyre: error: {bundled_tir(MF61)} with --set PKY1: the Magic Formula overflows (Fy, Mz, trail, "
        "cornering stiffness at 0.5-1.5 FNOMIN, 0.9-1.1 INFLPRES not finite): PKY1 = 1e+308; give it a value of a "
        "tyre's size")


def test_figures_that_come_out_non_finite_are_refused_naming_them_and_the_coefficient(
        capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    """The figures' own check, behind check_tyre_file's coarser one (switched off here)."""
    import virtsensor.tyres

    monkeypatch.setattr(virtsensor.tyres, "overflow_problem", lambda *args: None)
    assert _no_runtime_warning(["tyre", MF61, "--set", "PKY1=1e308"]) == 2
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err.strip() == (
        f"virtsensor tyre: error: {bundled_tir(MF61)} with --set PKY1: the Magic Formula overflows (the figures "
        "cornering stiffness, Fy peak, Mz peak at alpha > 0, Mz peak at alpha < 0, pneumatic trail at zero slip "
        "not finite): PKY1 = 1e+308; give it a value of a tyre's size")


def test_coefficients_of_a_file_that_overflow_together_are_named(tmp_path: Path,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    """Neither PKY1 nor PDY1 alone makes the figures finite again: both are named, in the file's order."""
    lines = bundled_tir(MFEVAL).read_text().splitlines()
    for i, ln in enumerate(lines):
        if ln.split("=")[0].strip() in ("PKY1", "PDY1"):
            lines[i] = f"{ln.split('=')[0].strip()} = 1e308"
    path = tmp_path / "huge.tir"
    path.write_text("\n".join(lines) + "\n")
    msg = _refused(capsys, path)
    assert msg.startswith(f"virtsensor tyre: error: {path}: the Magic Formula overflows (") and \
        msg.endswith("not finite): PDY1 = 1e+308, PKY1 = 1e+308; give them values of a tyre's size"), msg


def test_an_overflowing_rolling_resistance_is_refused_before_a_simulation(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """QSY7 = 1e300 leaves the figures finite but My not: 'virtsensor tyre' printed the figures, and a simulation
    with it ended in a traceback (an OverflowError of a Python float power, or a divergence at t = 0)."""
    path, line = _broken(tmp_path, "QSY7 = 1e300", "QSY7")
    expected = (f"{path}:{line}: the Magic Formula overflows (My at 0.5-1.5 FNOMIN, 0.9-1.1 INFLPRES not finite): "
                "QSY7 = 1e+300; give it a value of a tyre's size")
    assert _refused(capsys, path) == f"virtsensor tyre: error: {expected}"
    out = tmp_path / "dlc.csv"
    assert _no_runtime_warning(["simulate", "double-lane-change", "--speed", "80", "--mu", "1",
                                "--set", f"tyres.file={path}", "--out", str(out)]) == 2
    assert capsys.readouterr().err.strip() == f"virtsensor simulate: error: {expected}"
    assert not out.exists()


def test_missing_fittyp_and_units_are_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path, _ = _broken(tmp_path, "", "FITTYP")
    model_line = 1 + bundled_tir(MFEVAL).read_text().splitlines().index("[MODEL]")
    assert f"{path}:{model_line}: [MODEL] no FITTYP" in _refused(capsys, path)
    text = bundled_tir(MFEVAL).read_text()
    start, end = text.index("[UNITS]"), text.index("[MODEL]")
    path.write_text(text[:start] + text[end:])
    assert "no [UNITS] section" in _refused(capsys, path)


def test_optional_keys_left_out_take_defaults_and_are_listed(tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    path, _ = _broken(tmp_path, "", "LKY")
    figures = _figures(capsys, str(path))
    assert figures["defaults"] == {"LKY": 1.0, "LMUV": 0.0}
    assert main(["tyre", str(path)]) == 0
    assert "standard values used (2): LKY=1, LMUV=0" in capsys.readouterr().out
    reference = _figures(capsys, MFEVAL)  # the file gives LKY = 1: same figures
    assert _at(figures)["mz_max_nm"] == _at(reference)["mz_max_nm"]


def test_unknown_file_and_bad_set(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    msg = _refused(capsys, tmp_path / "nope.tir")
    assert "no such tyre property file" in msg and MFEVAL in msg
    assert "expected KEY=NUMBER" in _refused(capsys, bundled_tir(MF61), "--set", "LMUY")


def test_plot_and_json_files(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("matplotlib")
    png, js = tmp_path / "curves.png", tmp_path / "figures.json"
    assert main(["tyre", MF61, "--plot", str(png), "--json", str(js)]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 20_000
    assert _at(json.loads(js.read_text()))["mz_max_nm"] == pytest.approx(132.7, abs=0.1)
    assert "Mz peak" in capsys.readouterr().out
    assert sorted(p.name for p in tmp_path.iterdir()) == ["curves.png", "figures.json"]  # no partial files


_WITHOUT_EXTRAS = textwrap.dedent("""
    import importlib.abc, importlib.util, sys
    BLOCKED = {"sklearn", "skl2onnx", "scipy", "joblib", "tqdm", "threadpoolctl", "shap", "matplotlib"}
    class _NoExtras(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if name.split('.')[0] in BLOCKED:
                raise ModuleNotFoundError(f"No module named {name!r}", name=name)
            return None
    sys.meta_path.insert(0, _NoExtras())
    _find = importlib.util.find_spec
    importlib.util.find_spec = lambda n, *a: None if n.split('.')[0] in BLOCKED else _find(n, *a)
    from virtsensor.cli import main
    sys.exit(main(sys.argv[1:]))
""")


def test_runs_on_the_base_install_and_plot_names_the_extra(tmp_path: Path) -> None:
    """No optional extra is needed for the figures; --plot without matplotlib: one line naming 'plots'."""
    def run(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-c", _WITHOUT_EXTRAS, "tyre", MFEVAL, *args], capture_output=True,
                              text=True, cwd=tmp_path, timeout=120)

    ok = run("--json", "-")
    assert ok.returncode == 0, ok.stderr
    assert _at(json.loads(ok.stdout))["mz_max_nm"] == pytest.approx(117.5, abs=0.1)
    refused = run("--plot", "c.png")
    lines = refused.stderr.strip().splitlines()
    assert refused.returncode == 2 and len(lines) == 1 and "virtsensor[plots]" in lines[0], refused.stderr
    assert refused.stdout == "" and list(tmp_path.iterdir()) == []


# ----------------------------------------------------------------------------- --tyre on simulate / campaign
def test_simulate_with_mfeval_tyre_follows_its_curves(tmp_path: Path) -> None:
    """The SAT of a run with --tyre is the Mz of that file's curves, not the default tyre's."""
    from sim.params import car_parameters
    from sim.tyre import MagicFormula61
    from sim.vehicle import tyre_for
    from virtsensor.recordings.canlog import read_csv

    out = tmp_path / "dlc.csv"
    assert main(["simulate", "double-lane-change", "--speed", "80", "--mu", "1", "--seed", "1",
                 "--tyre", str(bundled_tir(MFEVAL)), "--out", str(out)]) == 0
    t = read_csv(out)
    car = car_parameters()
    ty = car["tyres"]
    # the right front tyre is a right-hand tyre (not mirrored); ground camber follows the body roll
    camber = ty["static_camber_front_rad"] + car["suspension"]["camber_roll_factor_front"] * t["roll_rad"]
    ops = (t["fz_fr_n"], t["kappa_fr_1"], t["alpha_fr_rad"], camber, t["vx_mps"], ty["pressure_front_pa"])
    rms = {}
    for name, model in (("mfeval", MagicFormula61.from_tir(bundled_tir(MFEVAL))), ("default", tyre_for(car))):
        rms[name] = float(np.sqrt(np.mean((t["sat_fr_nm"] - model.steady_state(*ops).mz) ** 2)))
    sat_rms = float(np.sqrt(np.mean(t["sat_fr_nm"] ** 2)))
    assert rms["mfeval"] < 0.05 * sat_rms, rms  # only the 20 Hz sampling of a 100 Hz transducer is left
    assert rms["default"] > 5.0 * rms["mfeval"], rms


def test_bad_tyre_option_is_refused_before_any_work(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path, line = _broken(tmp_path, "PKY1 = abc")
    out = tmp_path / "dlc.csv"
    assert main(["simulate", "double-lane-change", "--speed", "80", "--mu", "1", "--tyre", str(path),
                 "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{path}:{line}: cannot parse the value of PKY1" in err[0], err
    assert not out.exists()
    assert main(["simulate", "double-lane-change", "--speed", "80", "--mu", "1", "--tyre", MFEVAL,
                 "--set", f"tyres.file={bundled_tir(MF61)}", "--out", str(out)]) == 2
    assert "and --set tyres.file=... both name that tyre file" in capsys.readouterr().err
    camp = tmp_path / "camp"
    assert main(["campaign", "tiny", "--out", str(camp), "--tyre", str(tmp_path / "missing.tir")]) == 2
    assert "no such tyre property file" in capsys.readouterr().err
    assert not camp.exists()


def test_tyre_option_is_the_set_path(tmp_path: Path) -> None:
    """--tyre NAME gives the same parameter tree as --set tyres.file=<the bundled file>."""
    import argparse

    from virtsensor.commands._simargs import add_car_arguments, car_from_args

    parser = argparse.ArgumentParser()
    add_car_arguments(parser)
    by_option = car_from_args(parser.parse_args(["--tyre", MFEVAL.removesuffix(".tir")]))
    by_set = car_from_args(parser.parse_args(["--set", f"tyres.file={bundled_tir(MFEVAL).resolve()}"]))
    assert by_option == by_set


def test_tyre_option_per_axle() -> None:
    """--tyre rear=FILE / front=FILE set tyres.file_rear / file_front; a bare --tyre is all four wheels."""
    import argparse

    from virtsensor.commands._simargs import add_car_arguments, car_from_args

    parser = argparse.ArgumentParser()
    add_car_arguments(parser)

    def files(*argv: str) -> tuple[str, str, str]:
        ty = car_from_args(parser.parse_args(list(argv)))["tyres"]
        return tuple(Path(ty[k]).name if ty[k] else "" for k in ("file", "file_front", "file_rear"))  # type: ignore

    assert files("--tyre", f"rear={MFEVAL}") == ("c_segment_205_55R16.tir", "", MFEVAL)
    assert files("--tyre", f"front={MF61}", "--tyre", f"rear={MFEVAL}") == ("c_segment_205_55R16.tir", MF61, MFEVAL)
    assert files("--set", f"tyres.file_rear={bundled_tir(MF61)}", "--tyre", MFEVAL) == (MFEVAL, "", MF61)
    with pytest.raises(UserError, match="already given a tyre"):
        files("--tyre", f"rear={MFEVAL}", "--tyre", f"rear={MF61}")


@pytest.mark.slow
def test_simulate_with_a_different_rear_tyre(tmp_path: Path) -> None:
    """Only the rear axle changes: the front SAT still follows the default tyre's curves, the car does not."""
    from sim.params import car_parameters
    from sim.vehicle import tyre_for
    from virtsensor.recordings.canlog import read_csv

    runs = {}
    for name, extra in (("default", []), ("rear", ["--tyre", f"rear={MFEVAL}"])):
        out = tmp_path / f"{name}.csv"
        assert main(["simulate", "double-lane-change", "--speed", "80", "--mu", "1", "--seed", "1", *extra,
                     "--out", str(out)]) == 0
        runs[name] = read_csv(out)
    car = car_parameters()
    ty, t = car["tyres"], runs["rear"]
    camber = ty["static_camber_front_rad"] + car["suspension"]["camber_roll_factor_front"] * t["roll_rad"]
    front = tyre_for(car).steady_state(t["fz_fr_n"], t["kappa_fr_1"], t["alpha_fr_rad"], camber, t["vx_mps"],
                                       ty["pressure_front_pa"]).mz
    sat = t["sat_fr_nm"]
    assert float(np.sqrt(np.mean((sat - front) ** 2))) < 0.05 * float(np.sqrt(np.mean(sat**2)))
    assert float(np.max(np.abs(t["yaw_rate_radps"] - runs["default"]["yaw_rate_radps"]))) > 0.02


def test_a_tyre_file_that_is_a_pipe_is_not_called_missing(tmp_path, capsys):
    """``virtsensor tyre fifo.tir`` said "no such tyre property file" for a path that exists."""
    import os

    pipe = tmp_path / "fifo.tir"
    os.mkfifo(pipe)
    assert main(["tyre", str(pipe)]) == 2
    err = capsys.readouterr().err
    assert err.strip().endswith(f"{pipe}: not a regular file, give a .tir file") and err.count("\n") == 1, err
