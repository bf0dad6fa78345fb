"""The package installs as a package: lean runtime imports, package data, extras named when missing."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import zipfile
from pathlib import Path

import pytest
import tomllib

ROOT = Path(__file__).resolve().parents[1]
HEAVY = ("sklearn", "skl2onnx", "scipy", "sim", "joblib", "matplotlib", "shap", "tqdm")
#: the modules a daemon image imports to run: they must not pull in the training stack
RUNTIME_MODULES = ("virtsensor.daemon", "virtsensor.model", "virtsensor.model.onnx", "virtsensor.model.card",
                   "virtsensor.canbus.codec", "virtsensor.recordings.replay",
                   "virtsensor.features", "virtsensor.frontend", "virtsensor.assets", "virtsensor.cli")


def _pyproject() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())


def test_every_package_of_the_tree_is_listed_and_data_folders_are_mapped():
    tool = _pyproject()["tool"]["setuptools"]
    listed = set(tool["packages"])
    found = {".".join(p.parent.relative_to(ROOT).parts) for top in ("virtsensor", "sim")
             for p in (ROOT / top).rglob("__init__.py") if "__pycache__" not in p.parts}
    mapped = {name for name, folder in tool["package-dir"].items()}
    data = {".".join(p.relative_to(ROOT).parts) for p in (ROOT / "sim" / "data").rglob("*")
            if p.is_dir() and "__pycache__" not in p.parts} | {"sim.data"}  # (folders of data only)
    assert found <= listed, f"packages missing from pyproject.toml: {sorted(found - listed)}"
    assert data <= listed and set(tool["package-data"]) >= data, f"data folders not listed: {sorted(data - listed)}"
    assert listed - found - data == mapped, f"listed but not in the tree: {sorted(listed - found - mapped - data)}"
    for name, folder in tool["package-dir"].items():
        assert (ROOT / folder / "__init__.py").is_file(), name


def test_base_dependencies_are_the_runtime_only():
    deps = " ".join(_pyproject()["project"]["dependencies"]).lower()
    for heavy in ("scikit-learn", "skl2onnx", "scipy", "joblib", "tqdm", "matplotlib"):
        assert heavy not in deps, heavy


def test_runtime_imports_no_training_stack():
    code = textwrap.dedent(f"""
        import importlib, sys
        for m in {RUNTIME_MODULES!r}:
            importlib.import_module(m)
        print(",".join(sorted({{n.split('.')[0] for n in sys.modules}} & set({HEAVY!r}))))
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True)
    assert out.stdout.strip() == "", f"the runtime imports {out.stdout.strip()}"


_BLOCK = textwrap.dedent("""
    import importlib.abc, sys
    class _NoExtras(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if name.split('.')[0] in {blocked!r}:
                raise ModuleNotFoundError(f"No module named {{name!r}}", name=name)
            return None
    sys.meta_path.insert(0, _NoExtras())
    import importlib.util
    _find = importlib.util.find_spec
    importlib.util.find_spec = lambda n, *a: None if n.split('.')[0] in {blocked!r} else _find(n, *a)
    from virtsensor.cli import main
    sys.exit(main(sys.argv[1:]))
""")


@pytest.mark.parametrize("argv, extra", [
    (["train", "--data", "d", "--out", "m.onnx"], "train"),
    (["simulate", "fishhook", "--speed", "60", "--mu", "1", "--out", "x.csv"], "train"),
    (["explain", "--model", "m.onnx", "--data", "d", "--out", "f"], "explain"),
])
def test_a_command_whose_extra_is_missing_names_it_in_one_line(tmp_path, argv, extra):
    code = _BLOCK.format(blocked=("sklearn", "skl2onnx", "scipy", "joblib", "tqdm", "threadpoolctl", "shap",
                                  "matplotlib"))
    r = subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True, cwd=tmp_path)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and f"virtsensor[{extra}]" in lines[0], r.stderr
    assert "Traceback" not in r.stderr and list(tmp_path.iterdir()) == []


def test_the_missing_extra_is_named_once_with_what_pip_installs_and_the_help_still_reads(tmp_path):
    """``virtsensor train`` on the base install: one line that names the command once and the PyPI names
    (scikit-learn, not the module sklearn); ``train --help``, and the help of every other command of an extra, shows
    the options (exit 0) and which extra to install."""
    code = _BLOCK.format(blocked=("sklearn", "skl2onnx", "scipy", "joblib", "tqdm", "threadpoolctl", "shap",
                                  "matplotlib"))
    r = subprocess.run([sys.executable, "-c", code, "train"], capture_output=True, text=True, cwd=tmp_path)
    assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr
    assert r.stderr.count("virtsensor train") == 1 and "scikit-learn" in r.stderr and "sklearn" not in r.stderr
    h = subprocess.run([sys.executable, "-c", code, "train", "--help"], capture_output=True, text=True, cwd=tmp_path)
    flat = " ".join(h.stdout.split())  # (argparse wraps the epilog)
    assert h.returncode == 0 and "--data" in flat and "pip install 'virtsensor[train]'" in flat, h
    for name, option in (("simulate", "--track"), ("diagnose", "--measured"), ("campaign", "--out"),
                         ("evaluate", "--model"), ("explain", "--model")):  # (every command of an extra)
        s = subprocess.run([sys.executable, "-c", code, name, "--help"], capture_output=True, text=True,
                           cwd=tmp_path)
        flat = " ".join(s.stdout.split())
        assert s.returncode == 0 and option in flat and "pip install 'virtsensor[" in flat, (name, s.stderr)
        assert "Traceback" not in s.stderr, s.stderr
    s = subprocess.run([sys.executable, "-c", code, "simulate", "fishhook", "--mu", "1", "--out", "x.csv"],
                       capture_output=True, text=True, cwd=tmp_path)
    assert s.returncode == 2 and s.stderr.count("\n") == 1 and "virtsensor[train]" in s.stderr, s.stderr
    assert "scikit-learn" in s.stderr  # (every module of the extra that is missing, not the first one imported)
    for argv, code_ in ((["train", "--he"], 0), (["train", "--data", "d", "-h"], 0), (["train", "--out", "-h"], 2),
                        (["train", "--", "--help"], 2), (["evaluate", "--no-such-option"], 2)):
        a = subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True, cwd=tmp_path)
        assert a.returncode == code_, (argv, a.stderr)
        if code_ == 2:  # (whatever else the arguments hold: the extra first, in the one line)
            assert a.stderr.count("\n") == 1 and "needs the optional extra" in a.stderr, (argv, a.stderr)
        else:
            assert "virtsensor[train]" in " ".join(a.stdout.split()), (argv, a.stdout)
    assert "Traceback" not in r.stderr + h.stderr + s.stderr and list(tmp_path.iterdir()) == []


def test_a_missing_extra_found_while_a_command_runs_names_the_command_once(tmp_path):
    tir = ROOT / "sim" / "data" / "tyres" / "c_segment_205_55R16.tir"
    code = _BLOCK.format(blocked=("matplotlib",))
    r = subprocess.run([sys.executable, "-c", code, "tyre", str(tir), "--plot", str(tmp_path / "t.png")],
                       capture_output=True, text=True, cwd=tmp_path)
    assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr
    assert r.stderr.startswith("virtsensor tyre: error: --plot needs the optional extra 'plots'"), r.stderr
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
def test_the_built_wheel_runs_the_demo_and_the_daemon_from_an_empty_directory(tmp_path):
    """pip wheel, install it apart from the source tree, then run from an empty directory."""
    wheel_dir, site, empty = tmp_path / "wheel", tmp_path / "site", tmp_path / "empty"
    empty.mkdir()
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w",
                    str(wheel_dir), str(ROOT)], check=True, capture_output=True)
    (wheel,) = wheel_dir.glob("virtsensor-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    for asset in ("virtsensor/assets/models/improved.onnx", "virtsensor/assets/models/improved.card.json",
                  "virtsensor/assets/dbc/virtsensor.dbc"):
        assert asset in names, asset
    licences = {n.split("/licenses/", 1)[1] for n in names if ".dist-info/licenses/" in n}
    assert licences == {"LICENSE", "NOTICE", *(f"LICENSES/{p.name}" for p in (ROOT / "LICENSES").glob("*.txt"))}, \
        licences  # (the bundled third-party data ships with its licence texts)
    subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "-q", "--target", str(site), str(wheel)],
                   check=True, capture_output=True)
    env = {**os.environ, "PYTHONPATH": str(site)}
    probe = subprocess.run([sys.executable, "-c", "import virtsensor, sys; print(virtsensor.__file__)"],
                           capture_output=True, text=True, cwd=empty, env=env, check=True)
    assert probe.stdout.startswith(str(site)), probe.stdout  # the wheel, not the source tree
    demo = subprocess.run([sys.executable, "-m", "virtsensor.cli", "demo", "--rate", "max", "--no-live",
                           "--plot", "demo.png"], capture_output=True, text=True, cwd=empty, env=env, timeout=300)
    assert demo.returncode == 0, demo.stderr
    assert "MAE" in demo.stdout and "R2" in demo.stdout.replace("R²", "R2"), demo.stdout
    run = subprocess.run([sys.executable, "-m", "virtsensor.cli", "run", "--interface", "virtual", "--channel",
                          "pkgtest", "--duration", "0.5"], capture_output=True, text=True, cwd=empty, env=env,
                         timeout=120)
    assert run.returncode == 0, run.stderr
    assert '"started"' in run.stderr, run.stderr


def test_the_demo_runs_on_the_base_install(tmp_path):
    """The daemon, replay and demo need no optional extra: the training stack and matplotlib blocked."""
    code = _BLOCK.format(blocked=("sklearn", "skl2onnx", "scipy", "joblib", "tqdm", "threadpoolctl", "shap",
                                  "matplotlib"))
    r = subprocess.run([sys.executable, "-c", code, "demo", "--rate", "max", "--no-live"], capture_output=True,
                       text=True, cwd=tmp_path, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "MAE" in r.stdout and "Traceback" not in r.stderr


def test_the_bench_runs_on_the_base_install(tmp_path):
    """The bench replays shipped input frames: no simulator (scipy), no training stack, no matplotlib."""
    code = _BLOCK.format(blocked=("sklearn", "skl2onnx", "scipy", "joblib", "tqdm", "threadpoolctl", "shap",
                                  "matplotlib", "sim"))
    r = subprocess.run([sys.executable, "-c", code, "bench", "--quick", "--no-cross-process", "--no-cpu-latency",
                        "--soak-ticks", "200", "--quiet", "--json", "b.json"], capture_output=True, text=True,
                       cwd=tmp_path, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "Traceback" not in r.stderr and sorted(p.name for p in tmp_path.iterdir()) == ["b.json"]


def test_a_bench_histogram_without_matplotlib_is_refused_before_measuring(tmp_path):
    code = _BLOCK.format(blocked=("matplotlib",))
    r = subprocess.run([sys.executable, "-c", code, "bench", "--quick", "--no-cross-process", "--json", "b.json",
                        "--histogram", "h.png"], capture_output=True, text=True, cwd=tmp_path, timeout=120)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1 and "virtsensor[plots]" in lines[0], r.stderr
    assert list(tmp_path.iterdir()) == []
