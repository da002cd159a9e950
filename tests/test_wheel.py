"""A pip user gets the product (issue 23): the wheel built from the repository holds the package, its data and
the shipped detector; installed into a fresh virtual environment, away from the repository, its `torchskin`
runs `spectra` and `detect` (with the packaged default detector) from an empty folder.

The fresh environment reaches its requirements through a path file to this environment's site-packages (added
as a plain path: its own path files, among them this checkout's editable install, are not run), so the test
needs no network and still checks that the installed wheel, not the checkout, does the work."""

import json
import os
import shutil
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def wheel(tmp_path_factory):
    """The wheel, built from a copy of the sources the wheel is made of (so the checkout gets no build folder)."""
    src = tmp_path_factory.mktemp("src")
    for f in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy2(ROOT / f, src / f)
    shutil.copytree(ROOT / "torchskin", src / "torchskin", ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    dist = tmp_path_factory.mktemp("dist")
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index", "-q",
                        "-w", str(dist), str(src)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    (path,) = dist.glob("torchskin-*.whl")
    return path


@pytest.fixture(scope="module")
def fresh(wheel, tmp_path_factory):
    """A fresh virtual environment with the wheel installed (no pip of its own: this one installs into it)."""
    env = tmp_path_factory.mktemp("venv") / "fresh"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(env)], check=True, timeout=120)
    py = env / "bin" / "python"
    r = subprocess.run([sys.executable, "-m", "pip", "--python", str(py), "install", "--no-deps", "--no-index", "-q",
                        str(wheel)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    site = subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                          capture_output=True, text=True, check=True).stdout.strip()
    (Path(site) / "_requirements.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    return env


def _run(env, args, cwd):
    clean = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}
    return subprocess.run([str(env / "bin" / "torchskin"), *args], capture_output=True, text=True, timeout=300,
                          cwd=cwd, env=clean)


def test_the_wheel_holds_the_package_the_shipped_detector_and_the_licence(wheel):
    names = zipfile.ZipFile(wheel).namelist()
    assert "torchskin/data/detector.onnx" in names
    assert zipfile.ZipFile(wheel).read("torchskin/data/detector.onnx") == (ROOT / "exports" / "detector.onnx").read_bytes()
    assert any(n.endswith(".dist-info/licenses/LICENSE") for n in names), "no LICENSE in the wheel"
    assert {"torchskin/cli/__init__.py", "torchskin/onboard/__init__.py", "torchskin/onboard/runtime.py",
            "torchskin/py.typed"} <= set(names)
    meta = next(zipfile.ZipFile(wheel).read(n).decode() for n in names if n.endswith(".dist-info/METADATA"))
    assert "Requires-Dist: onnxruntime" in meta and "License-Expression: Apache-2.0" in meta
    assert "Project-URL: Source," in meta
    # README images render on a package index page: absolute links only
    assert "](docs/" not in meta and "](exports/" not in meta


def test_a_pip_user_runs_spectra_and_detect_from_an_empty_folder(fresh, tmp_path):
    """The user's first two commands, from the installed wheel alone: the skin model's reflectance of a type II
    skin in the detector's bands, then the shipped detector (no --model) on a frame holding a 10 x 10 patch of
    it: every patch pixel is skin, nothing else."""
    work = tmp_path / "empty"
    work.mkdir()
    where = subprocess.run([str(fresh / "bin" / "python"), "-c", "import torchskin; print(torchskin.__file__)"],
                           capture_output=True, text=True, cwd=work, check=True).stdout
    assert where.startswith(str(fresh)), where  # the installed wheel, not the checkout
    r = _run(fresh, ["spectra", "--preset", "II", "--bands", "544,633,1080,1580", "--json"], work)
    assert r.returncode == 0, r.stderr
    doc = json.loads(r.stdout)
    (skin,) = doc["skins"]
    refl = np.asarray(skin["reflectance"], dtype=np.float32)
    assert refl.shape == (4,) and 0.3 < refl[2] < 0.8 and refl[3] < refl[2]  # bright at 1080 nm, water-dark at 1580
    cube = np.full((4, 20, 20), 0.2, dtype=np.float32)
    cube[:, 5:15, 5:15] = refl[:, None, None]
    np.save(work / "frame.npy", cube)
    r = _run(fresh, ["detect", "--cube", "frame.npy", "--sun-zenith", "40", "--camera-zenith", "30",
                     "--relative-azimuth", "60", "--diffuse-share", "0.2", "--out", "mask.png", "--json"], work)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["skin_pixels"] == 100, out
    assert (work / "mask.png").is_file()
    assert sorted(p.name for p in work.iterdir()) == ["frame.npy", "mask.png"]
