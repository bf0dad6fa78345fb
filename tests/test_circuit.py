"""``simulate circuit``: any closed centreline (CSV x_m,y_m or GeoJSON lon/lat), its refusals,
the bundled development circuits, and the outcome every run records (completed, spun, stopped)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from sim import track as track_module
from sim.api import simulate, simulate_plan
from sim.campaign import manifest_entry
from sim.centreline import derive, equirectangular, read_points, track_from_points
from sim.driver import SPEED_OPEN, STEER_PATH, Plan
from sim.params import car_parameters
from sim.track import BUNDLED_TRACKS, TrackError, load_track
from virtsensor.cli import main

STATED_M = {"magny-cours": 4412.0, "hungaroring": 4381.0, "zandvoort": 4259.0, "red-bull-ring": 4318.0}


def stadium(radius: float = 30.0, straight: float = 80.0, step: float = 5.0) -> np.ndarray:
    """A stadium loop, counter-clockwise, first point on the lower straight (not repeated)."""
    pts = [(x, -radius) for x in np.arange(0.0, straight, step)]
    n = max(int(np.pi * radius / step), 6)
    pts += [(straight + radius * np.cos(a), radius * np.sin(a)) for a in np.linspace(-np.pi / 2, np.pi / 2, n + 1)[:-1]]
    pts += [(x, radius) for x in np.arange(straight, 0.0, -step)]
    pts += [(radius * np.cos(a), radius * np.sin(a)) for a in np.linspace(np.pi / 2, 1.5 * np.pi, n + 1)[:-1]]
    return np.array(pts)


def write_xy(path: Path, pts: np.ndarray) -> Path:
    path.write_text("x_m,y_m\n" + "".join(f"{x:.3f},{y:.3f}\n" for x, y in pts), encoding="utf-8")
    return path


def write_geojson(path: Path, pts: np.ndarray, lon0: float = 3.0, lat0: float = 47.0) -> Path:
    """The points as a GeoJSON LineString of lon/lat (inverse of the library's projection)."""
    unit = equirectangular(np.array([[lon0 + 1e-3, lat0 + 1e-3]]), lon0, lat0)[0] / 1e-3  # m per degree
    lonlat = np.column_stack([lon0 + pts[:, 0] / unit[0], lat0 + pts[:, 1] / unit[1]])
    coords = [[float(a), float(b)] for a, b in np.vstack([lonlat, lonlat[:1]])]  # closed, as published
    feature = {"type": "Feature", "properties": {"Name": "test"}, "geometry": {"type": "LineString",
                                                                            "coordinates": coords}}
    path.write_text(json.dumps({"type": "FeatureCollection", "features": [feature]}), encoding="utf-8")
    return path


# ---------------------------------------------------------------------- derivation
def test_csv_loop_is_closed_smoothed_and_keeps_its_direction(tmp_path: Path) -> None:
    pts = stadium()
    tr = load_track(write_xy(tmp_path / "oval.csv", pts))
    perimeter = 2 * 80.0 + 2 * np.pi * 30.0
    assert tr.length == pytest.approx(perimeter, rel=0.01)
    assert tr.turn_per_lap == pytest.approx(2 * np.pi, abs=1e-6)  # listed counter-clockwise: kept
    assert np.hypot(tr.x[-1] - tr.x[0], tr.y[-1] - tr.y[0]) < 1e-6
    assert np.abs(tr.curvature).max() == pytest.approx(1 / 30.0, rel=0.1)
    assert np.hypot(tr.x[0] - pts[0, 0], tr.y[0] - pts[0, 1]) < 0.5  # lap starts at the first point
    backwards = load_track(write_xy(tmp_path / "cw.csv", np.vstack([pts[:1], pts[:0:-1]])))
    assert backwards.turn_per_lap == pytest.approx(-2 * np.pi, abs=1e-6)


def test_geojson_lonlat_gives_the_same_circuit_as_metres(tmp_path: Path) -> None:
    pts = stadium()
    from_csv = load_track(write_xy(tmp_path / "oval.csv", pts))
    from_geo = load_track(write_geojson(tmp_path / "oval.geojson", pts))
    assert from_geo.length == pytest.approx(from_csv.length, rel=2e-3)
    assert from_geo.turn_per_lap == pytest.approx(from_csv.turn_per_lap)
    assert np.abs(from_geo.curvature).max() == pytest.approx(np.abs(from_csv.curvature).max(), rel=0.02)


def test_derive_can_force_a_direction() -> None:
    pts = stadium()
    cols, facts = derive(pts, direction="clockwise")
    assert facts["input_order"] == "counter-clockwise"
    assert cols["heading_rad"][-1] - cols["heading_rad"][0] == pytest.approx(-2 * np.pi, abs=1e-6)


SOURCES = Path(__file__).resolve().parent / "data" / "circuits"  # bacinger/f1-circuits GeoJSON (MIT, see NOTICE)
SOURCE_OF = {"magny-cours": "fr-1960", "hungaroring": "hu-1986", "zandvoort": "nl-1948", "red-bull-ring": "at-1969"}


@pytest.mark.parametrize("name", sorted(SOURCE_OF))
def test_bundled_circuits_are_the_librarys_derivation_of_their_source(name: str) -> None:
    """Every data row of a bundled centreline is what sim.centreline derives from its GeoJSON today."""
    import io

    points, _ = read_points(SOURCES / f"{SOURCE_OF[name]}.geojson")
    cols, _ = derive(points, direction="clockwise")
    buf = io.StringIO()
    np.savetxt(buf, np.column_stack([cols[c] for c in ("s_m", "x_m", "y_m", "heading_rad", "curvature_1pm")]),
               fmt=["%.4f", "%.4f", "%.4f", "%.8f", "%.8f"], delimiter=",")
    bundled = (Path(track_module.__file__).parent / "data" / BUNDLED_TRACKS[name]).read_text().splitlines()
    rows = [ln for ln in bundled if not ln.startswith("#")][1:]
    assert buf.getvalue().splitlines() == rows


def test_derive_track_tool_reproduces_the_magny_cours_file(tmp_path: Path) -> None:
    import subprocess
    import sys

    src = tmp_path / "magny-cours_fr-1960.geojson"
    src.write_bytes((SOURCES / "fr-1960.geojson").read_bytes())
    out = tmp_path / "sim" / "data" / "magny_cours_centreline.csv"
    root = Path(__file__).resolve().parent.parent
    subprocess.run([sys.executable, str(root / "tools" / "derive_track.py"), str(src),
                    "sim/data/magny_cours_centreline.csv"], cwd=tmp_path, check=True, capture_output=True, timeout=120)
    assert out.read_bytes() == (root / "sim" / "data" / "magny_cours_centreline.csv").read_bytes()


@pytest.mark.parametrize("name", sorted(BUNDLED_TRACKS))
def test_bundled_circuits_by_name(name: str) -> None:
    tr = load_track(name)
    assert abs(tr.length / STATED_M[name] - 1.0) < 0.015
    assert tr.turn_per_lap == pytest.approx(-2 * np.pi, abs=1e-6)  # all raced clockwise
    assert 1.0 / np.abs(tr.curvature).max() > 8.0
    assert np.allclose(np.diff(tr.s), np.diff(tr.s)[0], atol=2e-4)


# ---------------------------------------------------------------------- driving it
@pytest.fixture(scope="module")
def oval_run(tmp_path_factory: pytest.TempPathFactory):
    path = write_xy(tmp_path_factory.mktemp("oval") / "oval.csv", stadium())
    return simulate("circuit", 60.0, 1.0, seed=3, track=str(path), laps=1)


def test_small_circuit_is_driven_round_on_the_line(oval_run) -> None:
    truth, plan = oval_run.truth, oval_run.plan
    assert oval_run.outcome["status"] == "completed"
    assert truth["time_s"][-1] == pytest.approx(plan.duration_s, abs=0.02)
    path = plan.path
    d = np.min(np.hypot(truth["x_m"][:, None] - path[None, :, 0], truth["y_m"][:, None] - path[None, :, 1]), axis=1)
    assert d.max() < 2.0  # metres off the centreline
    past = np.hypot(truth["x_m"][-1] - path[-1, 0], truth["y_m"][-1] - path[-1, 1])
    assert past < truth["vx_true_mps"][-1] * 1.0 + 2.0  # back at the line (the run lasts the lap and 1 s more)
    # the corners (R 30 m) are taken at the speed profile's pace, well under the 60 km/h cap
    assert truth["vx_true_mps"].min() < 0.9 * 60 / 3.6
    assert np.abs(truth["ay_true_mps2"]).max() < 0.8 * 9.81
    assert oval_run.request.track and oval_run.request.laps == 1


@pytest.mark.slow
def test_simulate_circuit_cli_writes_the_run_and_its_outcome(tmp_path: Path, capsys) -> None:
    track = write_xy(tmp_path / "oval.csv", stadium())
    out = tmp_path / "run.csv"
    code = main(["simulate", "circuit", "--track", str(track), "--speed", "60", "--mu", "0.9", "--out", str(out)])
    assert code == 0 and out.exists()
    meta = json.loads((tmp_path / "run.json").read_text())
    assert meta["manoeuvre"] == "circuit" and meta["track"] == str(track) and meta["file"] == "run.csv"
    o = meta["outcome"]
    assert o["status"] == "completed" and o["driven_m"] > o["planned_m"] > 300.0
    assert f"completed ({o['driven_m']:.0f} m of {o['planned_m']:.0f} m driven)" in capsys.readouterr().err


# ---------------------------------------------------------------------- refusals
def _refused(argv: list[str], capsys, tmp_path: Path, fragment: str) -> None:
    before = set(tmp_path.iterdir())
    code = main(argv)
    err = capsys.readouterr().err
    assert code == 2
    assert len(err.strip().splitlines()) == 1 and fragment in err, err
    assert set(tmp_path.iterdir()) == before  # nothing written


def _circuit_argv(tmp_path: Path, track: str, *extra: str) -> list[str]:
    return ["simulate", "circuit", "--track", track, "--speed", "60", "--mu", "1.0",
            "--out", str(tmp_path / "run.csv"), *extra]


def test_refuses_an_open_centreline(tmp_path: Path, capsys) -> None:
    arc = np.array([(100 * np.cos(a), 100 * np.sin(a)) for a in np.linspace(0.0, np.pi, 60)])
    track = write_xy(tmp_path / "arc.csv", arc)
    _refused(_circuit_argv(tmp_path, str(track)), capsys, tmp_path, "open")


def _eight(length: float, width: float) -> np.ndarray:
    """A figure of eight, its crossing at the origin (first point), 200 points."""
    t = np.linspace(0.0, 2 * np.pi, 200, endpoint=False)
    return np.column_stack([length * np.sin(t), width * np.sin(2 * t)])


@pytest.mark.parametrize(("shape", "fragment"), [
    # the two passes 23 deg apart: no bridge, a trace out of order or two roads drawn on top of each other
    ("glancing", "at 23 deg, round a loop of 625 m"),
    # small loops round a circle: the knots a hairpin drawn too tightly leaves, 84 m round
    ("curls", "round a loop of 84 m"),
])
def test_refuses_a_self_intersecting_centreline(tmp_path: Path, capsys, shape: str, fragment: str) -> None:
    t = np.linspace(0.0, 2 * np.pi, 200, endpoint=False)
    pts = _eight(300.0, 30.0) if shape == "glancing" else \
        np.column_stack([150 * np.cos(t) + 40 * np.cos(6 * t), 150 * np.sin(t) + 40 * np.sin(6 * t)])
    track = write_xy(tmp_path / f"{shape}.csv", pts)
    _refused(_circuit_argv(tmp_path, str(track)), capsys, tmp_path, "crosses itself")
    _refused(_circuit_argv(tmp_path, str(track)), capsys, tmp_path, fragment)


@pytest.mark.slow
def test_a_figure_of_eight_crossing_at_a_bridge_is_driven(tmp_path: Path) -> None:
    """Suzuka (bacinger/f1-circuits jp-1962) crosses itself at 55 deg on a bridge, and was refused as "not a
    simple loop", although the driver finds the car along the road just ahead of it and drives it round.
    The same figure of eight the old refusal test used is now a lap, driven on its own pass through the
    crossing: the car's distance along the path never jumps (it would, by 300 m, onto the other pass)."""
    track = write_xy(tmp_path / "eight.csv", _eight(100.0, 50.0))
    tr = load_track(track)
    assert tr.turn_per_lap == pytest.approx(0.0, abs=1e-6)  # the two lobes turn opposite ways
    run = simulate("circuit", 60.0, 1.0, seed=3, track=str(track), laps=1)
    assert run.outcome["status"] == "completed"
    assert run.outcome["planned_m"] < run.outcome["driven_m"] < run.outcome["planned_m"] + 60 / 3.6
    truth, path = run.truth, run.plan.path
    # the car's nearest point on the path, searched just ahead of its last one (as the driver does)
    station, k = np.zeros(len(truth["x_m"]), dtype=int), 0
    for i, (x, y) in enumerate(zip(truth["x_m"], truth["y_m"], strict=True)):
        lo = max(k - 5, 0)
        k = lo + int(np.argmin(np.hypot(path[lo:k + 40, 0] - x, path[lo:k + 40, 1] - y)))
        station[i] = k
    off = np.hypot(truth["x_m"] - path[station, 0], truth["y_m"] - path[station, 1])
    assert off.max() < 2.0 and np.diff(station).min() >= -1
    assert station[-1] * run.plan.path_ds == pytest.approx(run.outcome["driven_m"], abs=3.0)


def test_refuses_a_too_short_centreline(tmp_path: Path, capsys) -> None:
    track = write_xy(tmp_path / "small.csv", stadium(radius=5.0, straight=20.0, step=2.0))
    _refused(_circuit_argv(tmp_path, str(track)), capsys, tmp_path, "shorter than")


def _magny_cours_points(scale: float) -> np.ndarray:
    """The bundled Magny-Cours centreline's points (about 4.4 km round), times ``scale``."""
    tr = load_track("magny-cours")
    return scale * np.column_stack([tr.x[:-1], tr.y[:-1]])


@pytest.mark.parametrize(("scale", "fragment"), [
    (1000.0, "the loop is 4444.76 km long, longer than the 50 km any circuit is (the longest, about 25 km); wrong "
             "unit? (coordinates in metres, not millimetres)"),
    (0.001, "the loop is 4.44 m long, shorter than the 200 m a circuit needs; wrong unit? (coordinates in metres, "
            "not kilometres)"),
])
def test_refuses_a_centreline_in_the_wrong_unit(tmp_path: Path, capsys, scale: float, fragment: str) -> None:
    """Magny-Cours in millimetres ran 170 s and took 20 GB before it was killed; in kilometres it was 'shorter
    than 200 m' with a length of 2 mm (the dense trace's moving average), and no hint."""
    track = tmp_path / "mc.csv"
    track.write_text("x_m,y_m\n" + "".join(f"{x:.9g},{y:.9g}\n" for x, y in _magny_cours_points(scale)))
    _refused(_circuit_argv(tmp_path, str(track)), capsys, tmp_path, f"{track}: {fragment}")


def test_refuses_a_huge_loop_before_any_work_is_sized_by_it(tmp_path: Path, capsys) -> None:
    """A circle of radius 1e9 m (400 points) asked for 46.8 GiB (one point a metre) before any check."""
    a = np.linspace(0.0, 2 * np.pi, 400, endpoint=False)
    track = write_xy(tmp_path / "big.csv", 1e9 * np.column_stack([np.cos(a), np.sin(a)]))
    _refused(_circuit_argv(tmp_path, str(track)), capsys, tmp_path, "km long, longer than the 50 km")
    with pytest.raises(TrackError, match=r"^big: the loop is 6283\.1\d km long, longer than the 50 km"):
        derive(1e6 * np.column_stack([np.cos(a), np.sin(a)]), origin="big")


def test_refuses_a_derived_centreline_in_the_wrong_unit(tmp_path: Path, capsys) -> None:
    """A centreline already derived (s_m,x_m,y_m,heading_rad,curvature_1pm, used as is) in millimetres."""
    tr = load_track("magny-cours")
    path = tmp_path / "mc_derived.csv"
    rows = np.column_stack([1000.0 * tr.s, 1000.0 * tr.x, 1000.0 * tr.y, tr.heading, tr.curvature / 1000.0])
    path.write_text("s_m,x_m,y_m,heading_rad,curvature_1pm\n" + "".join(",".join(f"{v:.6f}" for v in row) + "\n"
                                                                      for row in rows))
    _refused(_circuit_argv(tmp_path, str(path)), capsys, tmp_path, "km long, longer than the 50 km any circuit is")


def test_a_loop_as_long_as_the_longest_circuits_is_accepted() -> None:
    """26 km (the Nordschleife with the GP circuit is 25.4 km): derived, neither too long nor too big to derive."""
    a = np.linspace(0.0, 2 * np.pi, 1300, endpoint=False)
    r = 26_000.0 / (2 * np.pi)
    cols, facts = derive(np.column_stack([r * np.cos(a), 0.6 * r * np.sin(a)]))
    assert 20_000.0 < facts["length_m"] < 50_000.0 and len(cols["s_m"]) == facts["n_samples"] + 1


def test_refuses_a_corner_too_tight_for_the_car(tmp_path: Path, capsys) -> None:
    track = write_xy(tmp_path / "hairpin.csv", stadium(radius=4.0, straight=150.0, step=2.0))
    _refused(_circuit_argv(tmp_path, str(track)), capsys, tmp_path, "tighter than the car")


def test_a_less_steerable_car_finds_a_wide_corner_too_tight(tmp_path: Path, capsys) -> None:
    track = write_xy(tmp_path / "oval.csv", stadium())
    _refused(_circuit_argv(tmp_path, str(track), "--set", "steering.max_road_wheel_angle_rad=0.1"),
             capsys, tmp_path, "tighter than the car")


@pytest.mark.parametrize(("content", "fragment"), [
    ("x,y\n0,0\n", "expected a header line x_m,y_m"),
    ("x_m,y_m\n0,0\n10,zero\n", "line 3"),
    ("x_m,y_m\n0,0\n10,0\n", "at least 4 distinct points"),
    ("x_m,y_m\n0,0\n300,0\n300,300\n0,30", "line 5: truncated: the file ends inside this row"),
    ("x_m,y_m\n0,0\n300,0\n# the end, no newline", "at least 4 distinct points"),  # (a comment is no row)
    ("s_m,x_m,y_m,heading_rad,curvature_1pm\n0,0,0,0,0\n1,1,0,0,x\n", "line 3: curvature_1pm 'x' is not a number"),
    ("s_m,x_m,y_m,heading_rad,curvature_1pm\n0,0,0,0,0\n1,1,0,0,0\n2,2,0,0,0", "line 4: truncated"),
    ("s_m,x_m,y_m,heading_rad,curvature_1pm\n0,0,0,0,0\n", "at least 3 samples"),
])
def test_refuses_a_malformed_csv(tmp_path: Path, capsys, content: str, fragment: str) -> None:
    track = tmp_path / "bad.csv"
    track.write_text(content)
    _refused(_circuit_argv(tmp_path, str(track)), capsys, tmp_path, fragment)


def test_refuses_geojson_without_a_linestring(tmp_path: Path, capsys) -> None:
    track = tmp_path / "point.geojson"
    track.write_text(json.dumps({"type": "Feature", "geometry": {"type": "Point", "coordinates": [3.0, 47.0]}}))
    _refused(_circuit_argv(tmp_path, str(track)), capsys, tmp_path, "no LineString")


@pytest.mark.parametrize(("argv_tail", "fragment"), [
    (["circuit", "--speed", "60", "--mu", "1"], "--track"),
    (["circuit", "--track", "nowhere-ring", "--speed", "60", "--mu", "1"], "unknown circuit 'nowhere-ring'"),
    (["circuit", "--track", "missing.csv", "--speed", "60", "--mu", "1"], "no such file"),
    (["circuit", "--track", "zandvoort", "--laps", "0", "--speed", "60", "--mu", "1"], "--laps"),
    (["circuit", "--track", "zandvoort", "--speed", "300", "--mu", "1"], "outside circuit's range"),
    (["fishhook", "--track", "zandvoort", "--speed", "60", "--mu", "1"], "go with the manoeuvre 'circuit'"),
])
def test_refuses_bad_options(tmp_path: Path, capsys, argv_tail: list[str], fragment: str) -> None:
    _refused(["simulate", *argv_tail, "--out", str(tmp_path / "run.csv")], capsys, tmp_path, fragment)


def test_library_refusal_names_the_origin() -> None:
    with pytest.raises(TrackError, match="my-loop: .*open"):
        track_from_points(np.array([(100 * np.cos(a), 100 * np.sin(a)) for a in np.linspace(0, 3, 50)]), "my-loop")


def _straight_plan(mu: float, grip: tuple[float, float] | None) -> Plan:
    """4 s along a straight whose speed profile asks for 3 m/s^2, on a road of friction ``mu``."""
    ds = 2.0
    s = np.arange(0.0, 300.0, ds)
    t = Plan.grid(4.0)
    n = len(t)
    return Plan("straight", 4.0, 8.0, np.full(n, STEER_PATH, np.int8), np.zeros(n), np.zeros(n, np.int8),
                np.full(n, 8.0), np.zeros(n), np.zeros(n), path=np.column_stack([s, np.zeros_like(s)]),
                path_speed=np.minimum(np.sqrt(64.0 + 6.0 * s), 30.0), path_ds=ds, mu_values=(mu,), path_grip=grip)


@pytest.mark.slow
def test_the_track_driver_does_not_spin_the_driven_wheels_on_a_wet_road() -> None:
    """Asked for more acceleration than a wet road gives the front axle, the track driver
    feathers the throttle (``path_grip``); the same plan without it spins the front wheels."""
    from sim.manoeuvres import TRACK_GRIP

    for grip, spins in ((None, True), (TRACK_GRIP, False)):
        run = simulate_plan(_straight_plan(0.2, grip))
        slip = np.maximum(np.abs(run.truth["kappa_fl"]), np.abs(run.truth["kappa_fr"]))
        assert (slip.max() > 0.3) == spins, (grip, slip.max())
    assert run.truth["ax_true_mps2"].max() < 0.5 * 0.2 * 9.81  # within the front axle's grip (60 % of the load)
    assert run.truth["vx_true_mps"][-1] > 8.0 + 2.0  # it still gains speed


# ---------------------------------------------------------------------- outcome
def _open_loop_plan(duration_s: float, speed0: float, steer_rad: float, brake_nm: float, mu: float) -> Plan:
    """Steer to ``steer_rad`` at 0.5 s, brake with ``brake_nm`` per front wheel from 1 s."""
    t = Plan.grid(duration_s)
    n = len(t)
    return Plan("open-loop", duration_s, speed0, np.zeros(n, np.int8), np.where(t > 0.5, steer_rad, 0.0),
                np.full(n, SPEED_OPEN, np.int8), np.full(n, speed0), np.zeros(n), np.where(t > 1.0, brake_nm, 0.0),
                mu_values=(mu,))


def test_a_spun_run_says_so_and_when(tmp_path: Path) -> None:
    # braking in a turn with most of the braking on the rear axle: the rear locks and the car spins
    params = car_parameters(["brakes.front_share=0.2"])
    run = simulate_plan(_open_loop_plan(6.0, 25.0, 1.0, 800.0, 0.5), params)
    out = run.outcome
    assert out["status"] == "spun"
    assert 1.0 < out["at_s"] < out["planned_s"] == 6.0
    assert run.truth["time_s"][-1] == pytest.approx(out["at_s"])
    entry = manifest_entry(run, tmp_path / "x.csv", samples=10, duration_s=1.0)
    assert entry["outcome"] == out and "track" not in entry


def test_a_stopped_run_says_so() -> None:
    run = simulate_plan(_open_loop_plan(6.0, 8.0, 0.0, 1500.0, 1.0))  # hard braking from 29 km/h
    assert run.outcome["status"] == "stopped" and run.outcome["at_s"] < 5.0


def test_a_car_off_the_track_ends_the_run(tmp_path: Path) -> None:
    from sim.manoeuvres import TRACK_HALF_WIDTH_M, build_plan

    track = write_xy(tmp_path / "oval.csv", stadium())
    plan = build_plan("circuit", 60.0, 1.0, 0, car_parameters(), track=str(track))
    plan.path = plan.path + np.array([0.0, TRACK_HALF_WIDTH_M + 2.0])  # the car starts beside the track
    run = simulate_plan(plan)
    assert run.outcome["status"] == "off-track" and run.outcome["at_s"] < 0.5


def test_a_complete_run_says_so() -> None:
    run = simulate_plan(_open_loop_plan(2.0, 20.0, 0.2, 0.0, 1.0))
    assert run.outcome == {"status": "completed", "at_s": 2.0, "planned_s": 2.0}


def test_a_lap_driven_to_plan_is_completed_with_its_distance(oval_run) -> None:
    out = oval_run.outcome
    lap = oval_run.plan.label["lap_length_m"]
    assert out["status"] == "completed" and out["planned_m"] == pytest.approx(lap, abs=0.1)
    # past the line by the plan's last second, less the speed loop's lag
    assert out["planned_m"] < out["driven_m"] < out["planned_m"] + 60 / 3.6


@pytest.mark.slow
def test_a_car_that_falls_behind_its_plan_says_so_and_how_far_it_got(tmp_path: Path, capsys) -> None:
    """A crippled motor (10 Nm, the least a car may have) cannot hold the speed profile: when the planned time
    runs out the lap is not driven. The run is whole (every planned sample) but ``behind-plan``, not ``completed``."""
    track = write_xy(tmp_path / "oval.csv", stadium())
    out = tmp_path / "slow.csv"
    assert main(["simulate", "circuit", "--track", str(track), "--speed", "60", "--mu", "1",
                 "--set", "powertrain.motor_max_torque_nm=10", "--out", str(out)]) == 0
    meta = json.loads((tmp_path / "slow.json").read_text())
    o = meta["outcome"]
    assert o["status"] == "behind-plan" and o["at_s"] == pytest.approx(o["planned_s"], abs=0.01)
    assert o["planned_m"] == pytest.approx(meta["label"]["lap_length_m"], abs=0.1)
    assert 0.5 * o["planned_m"] < o["driven_m"] < 0.95 * o["planned_m"]
    assert meta["duration_s"] == pytest.approx(o["planned_s"], abs=0.1)  # a whole recording (20 Hz)
    err = capsys.readouterr().err
    share = f"{100 * o['driven_m'] / o['planned_m']:.1f} %"
    assert f"BEHIND PLAN: {o['driven_m']:.0f} m of {o['planned_m']:.0f} m driven ({share})" in err
    assert "completed" not in err


def _frozen_after_end(plans: list[Plan], params: list[dict]) -> tuple[list, list, list]:
    """Simulate ``plans`` in one batch; per run, the states the driver saw (every control step), and
    the RuntimeWarnings raised."""
    import warnings

    from sim.driver import Driver
    from sim.engine import simulate_batch

    seen: list[np.ndarray] = []
    update = Driver.update

    def spy(self, k, x):
        seen.append(x.copy())
        return update(self, k, x)

    with warnings.catch_warnings(record=True) as caught, pytest.MonkeyPatch.context() as mp:
        warnings.simplefilter("always")
        mp.setattr(Driver, "update", spy)
        res = simulate_batch(plans, params)
    states = np.stack(seen, axis=1)  # (B, steps, state)
    return [res.outcome(i) for i in range(len(plans))], states, [w for w in caught if w.category is RuntimeWarning]


@pytest.mark.slow
def test_a_run_that_ended_stays_where_it_ended_while_the_batch_goes_on() -> None:
    """A spun run is not integrated on while a longer run of its batch is (integrated on, a spun car
    diverges until numpy overflows; ``test_a_spun_circuit_run_in_a_long_batch_warns_nothing``)."""
    spin = _open_loop_plan(6.0, 25.0, 1.0, 800.0, 0.5)
    straight = _open_loop_plan(8.0, 20.0, 0.0, 0.0, 1.0)
    outcomes, states, warned = _frozen_after_end([spin, straight], [car_parameters(["brakes.front_share=0.2"]),
                                                                    car_parameters()])
    assert [o["status"] for o in outcomes] == ["spun", "completed"] and not warned
    ended = int(round(outcomes[0]["at_s"] / 0.01)) + 2
    assert states.shape[1] == 801 and ended < 600
    assert np.array_equal(states[0, ended:], np.broadcast_to(states[0, ended], states[0, ended:].shape))
    assert not np.array_equal(states[1, ended], states[1, -1])  # the other run goes on


@pytest.mark.slow
def test_a_spun_circuit_run_in_a_long_batch_warns_nothing(tmp_path: Path) -> None:
    """The ``circuits`` campaign case: a random circuit spun on a rear tyre of 0.75 times the grip (at 2.4 s, when
    its line lay inside a corner; at 14.3 s since the line moves on to the next straight) and, integrated on beside
    a longer run, overflowed 77 s later (RuntimeWarnings from the tyre and body)."""
    import warnings

    from sim.api import Request, simulate_many
    from sim.params import resolve_data_file

    tir = resolve_data_file("tyres/c_segment_205_55R16.tir").read_text()
    low = tmp_path / "low.tir"
    low.write_text(tir.replace("LMUX = 1 ", "LMUX = 0.75 ").replace("LMUY = 1 ", "LMUY = 0.75 "))
    oval = write_xy(tmp_path / "oval.csv", stadium())
    requests = [Request("circuit", 170.0, 1.0, 0, track="random:2995255897", laps=1),
                Request("circuit", 60.0, 1.0, 0, track=str(oval), laps=4)]  # 95 s
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        runs = simulate_many(requests, car_parameters([f"tyres.file_rear={low}"]))
    assert [r.outcome["status"] for r in runs] == ["spun", "completed"]
    assert runs[0].outcome["at_s"] < runs[1].outcome["at_s"] - 60.0  # (a minute and more integrated beside it)
    assert not [w for w in caught if w.category is RuntimeWarning], [str(w.message) for w in caught]


@pytest.mark.slow
def test_random_circuits_are_deterministic_drivable_and_track_like():
    """random:SEED circuits: the same for a seed, closed, never self-crossing (star-shaped), with corners
    like a grand-prix circuit's (the module docstring's figures)."""
    import numpy as np

    from sim.randomtrack import random_track
    from sim.track import TrackError, load_track

    a, b = load_track("random:7"), random_track(7)
    assert np.array_equal(a.x, b.x) and np.array_equal(a.curvature, b.curvature)
    stats = []
    for seed in range(16):
        tr = random_track(seed)
        k = np.abs(tr.curvature)
        assert 2400 < tr.length < 5700 and 1.0 / k.max() >= 10.0
        stats.append((1.0 / k.max(), (k > 1 / 40).mean(), (k > 1 / 100).mean(), (k > 1 / 300).mean()))
    s = np.array(stats)
    assert 10.0 <= np.median(s[:, 0]) <= 25.0
    assert 0.03 <= s[:, 1].mean() <= 0.10 and 0.12 <= s[:, 2].mean() <= 0.30 and 0.28 <= s[:, 3].mean() <= 0.55
    with pytest.raises(TrackError, match="random:SEED"):
        load_track("random:x")


def test_a_line_inside_a_corner_is_moved_on_to_the_next_straight(tmp_path: Path) -> None:
    """A car starts going straight: on a centreline whose first point is inside a corner (a circuit traced from
    its first GPS point, a random circuit) the path follower asked for the whole corner's lock at once (0 to 120
    degrees of steering in 0.15 s on a random circuit of campaign ``circuits``, the hand torque near the CAN
    range). The line moves on to the next straight; the circuit is the same."""
    from sim.manoeuvres import circuit

    pts = stadium()
    k = len(pts) // 4 + 3  # (inside the first semicircle)
    corner = write_xy(tmp_path / "corner.csv", np.roll(pts, -k, axis=0))
    tr = load_track(str(corner))
    assert abs(tr.curvature[0]) > 0.02  # (R 30 m)
    s0 = tr.next_straight()
    assert 0.0 < s0 < tr.length / 2
    moved = tr.started_at(s0)
    assert moved.length == tr.length and moved.turn_per_lap == pytest.approx(tr.turn_per_lap)
    assert np.abs(moved.curvature[: int(10 / (moved.s[1] - moved.s[0]))]).max() <= 0.002
    for s in (0.0, 17.0, 150.0, tr.length - 40.0):  # the same road, driven from elsewhere
        a, b = tr.at(s0 + s), moved.at(s)
        assert np.hypot(a.x - b.x, a.y - b.y) < 1e-6 and a.curvature == pytest.approx(b.curvature, abs=1e-9)
    mid = write_xy(tmp_path / "oval.csv", np.roll(pts, -8, axis=0))  # (40 m down the 80 m straight)
    assert load_track(str(mid)).next_straight() == 0.0
    plan = circuit(60 / 3.6, 1.0, np.random.default_rng(0), car_parameters(), track=str(corner))
    assert plan.label["line_moved_m"] == pytest.approx(s0, abs=0.05)
    head = np.hypot(*(plan.path[1:10] - plan.path[:9]).T)
    turn = np.abs(np.diff(np.unwrap(np.arctan2(*(plan.path[1:11] - plan.path[:10]).T[::-1]))))
    assert (turn / head).max() < 0.003  # (the path the car starts on is straight)


def test_a_centreline_that_is_no_readable_file_is_named_as_such(tmp_path: Path, capsys, monkeypatch) -> None:
    """A pipe was "no such file", and a file the user may not read ended the command as a machine failure (exit 1,
    a bare "Permission denied")."""
    import builtins
    import os

    pipe = tmp_path / "pipe.csv"
    os.mkfifo(pipe)
    with pytest.raises(TrackError, match=r"pipe\.csv: not a regular file$"):
        load_track(str(pipe))
    locked = write_xy(tmp_path / "locked.geojson", stadium())
    real_open = builtins.open

    def guarded(file, *a, **k):
        if str(file) == str(locked):
            raise PermissionError(13, "Permission denied", str(file))
        return real_open(file, *a, **k)

    monkeypatch.setattr(builtins, "open", guarded)
    assert main(["simulate", "circuit", "--track", str(locked), "--speed", "100", "--mu", "0.5", "--out",
                 str(tmp_path / "o.csv")]) == 2
    err = capsys.readouterr().err
    assert err.strip().endswith("locked.geojson: not readable (Permission denied)") and err.count("\n") == 1, err
