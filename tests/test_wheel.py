"""The built wheel works anywhere: installed alone into a fresh venv outside the checkout, `pavemap demo` and a
KITTI import + run find the shipped detector inside the package and write nothing into the working directory.

The venv's third-party packages come from the development venv's site-packages (a ``.pth`` line: no
network, no second install of torch), but pavemap itself only from the wheel: the development venv's
editable install (its ``__editable__`` .pth, processed only in a real site dir) is not seen, and the test
asserts ``pavemap.__file__`` lies in the new venv. Select with ``pytest -m wheel``; it takes minutes.
"""

from __future__ import annotations

import os
import shutil
import site
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

from pavemap.weights.registry import SHIPPED_WEIGHTS
from qgis_support import SURVEY, check_styles

REPO = Path(__file__).resolve().parents[1]
KITTI = REPO.parent / "shared" / "data" / "kitti-odometry-sample"
#: what the wheel must carry besides the code (package data, pyproject's [tool.setuptools.package-data])
PACKAGE_DATA = (f"pavemap/weights/{SHIPPED_WEIGHTS}", "pavemap/weights/MODEL_CARD.md",
                "pavemap/configs/maintenance_policy.yaml", "pavemap/assets/__init__.py")


def build_wheel(out: Path) -> Path:
    """Build sdist and wheel (the wheel from the sdist, as pip does) from a copy of the tracked sources, so
    the checkout gets no build/ or egg-info; no isolation: the build backend comes from this venv, offline."""
    src = out / "src-copy"
    files = subprocess.run(["git", "ls-files", "pyproject.toml", "README.md", "src"], cwd=REPO, check=True,
                           capture_output=True, text=True).stdout.split()
    for f in files:
        (src / f).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(REPO / f, src / f)
    r = subprocess.run([sys.executable, "-m", "build", "--no-isolation", "--skip-dependency-check", "--outdir",
                        str(out / "dist"), str(src)], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    wheels = list((out / "dist").glob("pavemap-*.whl"))
    assert len(wheels) == 1 and list((out / "dist").glob("pavemap-*.tar.gz")), list((out / "dist").iterdir())
    return wheels[0]


def missing_package_data(wheel: Path) -> list[str]:
    names = set(zipfile.ZipFile(wheel).namelist())
    return [f for f in PACKAGE_DATA if f not in names]


def make_venv(root: Path, wheel: Path) -> Path:
    """A venv whose pavemap is the wheel's and whose dependencies are this venv's site-packages; its bin/."""
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(root)], check=True, timeout=120)
    py = root / "bin" / "python"
    purelib = Path(subprocess.run([py, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                                  check=True, capture_output=True, text=True).stdout.strip())
    deps = [p for p in {sysconfig.get_paths()["purelib"], *site.getsitepackages()} if Path(p).is_dir()]
    # one line per folder; the editable install's .pth there is NOT processed (only site dirs' .pth are)
    (purelib / "zz_pavemap_test_deps.pth").write_text("".join(f"{p}\n" for p in deps))
    # without PYTHONPATH: a source tree on it would make pip see pavemap as installed already
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    r = subprocess.run([sys.executable, "-m", "pip", "--python", str(py), "install", "-q", "--no-deps", "--no-index",
                        str(wheel)], capture_output=True, text=True, timeout=300, env=env)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    return root / "bin"


def clean_env(home: Path, bindir: Path) -> dict[str, str]:
    """A user account of its own: HOME and XDG folders in tmp, no PYTHONPATH (it would bring src/ back)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PAVEMAP_", "YOLO_", "XDG_"))
           and k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}
    env.update(HOME=str(home), XDG_CACHE_HOME=str(home / ".cache"), XDG_DATA_HOME=str(home / ".local" / "share"),
               XDG_CONFIG_HOME=str(home / ".config"), MPLCONFIGDIR=str(home / ".mpl"),
               PATH=f"{bindir}{os.pathsep}{env.get('PATH', '')}", OMP_NUM_THREADS="2")
    return env


def run(cmd: list[str], cwd: Path, env: dict[str, str], timeout: int = 900) -> str:
    r = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert r.returncode == 0, f"{' '.join(cmd)} -> {r.returncode}\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
    return r.stdout + r.stderr


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """(bin folder of a fresh venv holding only the wheel's pavemap, its env, the wheel)."""
    root = tmp_path_factory.mktemp("wheel")
    wheel = build_wheel(root)
    bindir = make_venv(root / "venv", wheel)
    return bindir, clean_env(root / "home", bindir), wheel


@pytest.mark.wheel
def test_the_wheel_carries_the_weights_and_its_data(installed):
    _, _, wheel = installed
    assert missing_package_data(wheel) == []


@pytest.mark.wheel
def test_a_wheel_without_its_weights_is_caught(installed, tmp_path):
    """The check can fail: the same wheel with the weights taken out fails both the file-list check and a
    run of the default detector (`pavemap weights verify`, exit status 1 naming the file)."""
    bindir, env, wheel = installed
    stripped = tmp_path / wheel.name
    with zipfile.ZipFile(wheel) as zin, zipfile.ZipFile(stripped, "w", zipfile.ZIP_DEFLATED) as zout:
        for item in zin.infolist():
            if not item.filename.endswith(SHIPPED_WEIGHTS):
                zout.writestr(item, zin.read(item.filename))
    assert missing_package_data(stripped) == [f"pavemap/weights/{SHIPPED_WEIGHTS}"]
    venv = make_venv(tmp_path / "venv", stripped)
    cwd = tmp_path / "cwd"
    cwd.mkdir()
    r = subprocess.run([str(venv / "pavemap"), "weights", "verify"], cwd=cwd, env=clean_env(tmp_path / "h", venv),
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 1 and f"{SHIPPED_WEIGHTS}: missing" in r.stderr, r.stdout + r.stderr


@pytest.mark.wheel
def test_demo_and_a_kitti_run_from_the_wheel_write_only_under_out(installed, tmp_path):
    bindir, env, _ = installed
    cwd, work = tmp_path / "empty-cwd", tmp_path / "work"
    cwd.mkdir()
    py = str(bindir / "python")
    where = run([py, "-c", "import pavemap, pavemap.detect.backends as b; print(pavemap.__file__); "
                 "print(b.shipped_weights())"], cwd, env).split()
    assert all(w.startswith(str(bindir.parent)) for w in where), where  # the wheel's, not /work/main/src
    assert "ok" in run([str(bindir / "pavemap"), "weights", "verify"], cwd, env)
    # the demo with the shipped YOLO detector instead of the simulated one (no epochs to train there anyway)
    out = run([str(bindir / "pavemap"), "demo", "--out", str(work / "demo"), "--set", "detector.backend=yolo",
               "detector.imgsz=320"], cwd, env)
    assert SHIPPED_WEIGHTS in out and (work / "demo" / "run" / "survey.gpkg").is_file(), out[-2000:]
    check_styles(work / "demo" / "run" / "survey.gpkg", SURVEY)  # the QGIS styles come with the wheel's writer
    if KITTI.is_dir():
        run([str(bindir / "pavemap"), "import", "kitti", str(KITTI), "--sequence", "90", "--camera", "0",
             "--no-lidar", "--stop", "20", "-o", str(work / "kitti")], cwd, env)
        out = run([str(bindir / "pavemap"), "run", str(work / "kitti"), "-o", str(work / "kitti-run"), "-c", "kitti",
                   "--set", "detector.imgsz=320"], cwd, env)
        assert SHIPPED_WEIGHTS in out and (work / "kitti-run" / "report.html").is_file(), out[-2000:]
    assert sorted(p.name for p in cwd.iterdir()) == []  # no .yolo/, no cache, nothing
    assert (Path(env["XDG_CACHE_HOME"]) / "pavemap" / "ultralytics").is_dir()  # the user cache took it


def test_cheap_commands_write_nothing_into_the_working_directory(tiny_seq, tmp_path):
    """`pavemap info` and `pavemap weights list` from an empty folder, a user account of their own (this checkout's
    pavemap, as the tests run it)."""
    cwd, home = tmp_path / "cwd", tmp_path / "home"
    cwd.mkdir()
    env = clean_env(home, Path(sys.executable).parent)
    env["PYTHONPATH"] = str(REPO / "src")
    for cmd in (["info", str(tiny_seq.root)], ["weights", "list"], ["weights", "verify"]):
        run([sys.executable, "-m", "pavemap.cli", *cmd], cwd, env, timeout=300)
    assert list(cwd.iterdir()) == []
