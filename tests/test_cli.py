"""The `torchskin` command line: JSON contract, plots, errors."""

import json
import math
import subprocess
import sys

import pytest

from torchskin import tissue
from torchskin.cli import main
from torchskin.detect import DEFAULT_BOX


def run_json(capsys, *args):
    assert main(list(args)) == 0
    return json.loads(capsys.readouterr().out)


def test_spectra_json_contract(capsys):
    out = run_json(capsys, "spectra", "--preset", "I-II", "--preset", "V-VI", "--bands", "544,633,1080,1580",
                   "--json")
    skins = out["skins"]
    assert [s["name"] for s in skins] == ["I-II", "V-VI"]
    for s in skins:
        assert set(s) >= {"name", "params", "wavelengths_nm", "reflectance", "ndgri", "ndsi"}
        assert s["wavelengths_nm"] == [544.0, 633.0, 1080.0, 1580.0]
        g, r, n, w = s["reflectance"]
        assert abs(s["ndgri"] - (g - r) / (g + r)) < 1e-9 and abs(s["ndsi"] - (n - w) / (n + w)) < 1e-9
        assert DEFAULT_BOX.b1 <= s["ndgri"] <= DEFAULT_BOX.b2
    assert skins[0]["params"]["melanosome"] == pytest.approx(0.035)


def test_spectra_indices_always_at_default_bands(capsys):
    a = run_json(capsys, "spectra", "--preset", "III", "--wavelengths", "400:700:50", "--json")["skins"][0]
    b = run_json(capsys, "spectra", "--preset", "III", "--bands", "544,633,1080,1580", "--json")["skins"][0]
    assert len(a["wavelengths_nm"]) == 7 and a["ndgri"] == pytest.approx(b["ndgri"]) and a["ndsi"] == b["ndsi"]


def test_spectra_sample_param_and_incidence(capsys):
    out = run_json(capsys, "spectra", "--sample", "20", "--seed", "3", "--param", "oxygenation=0.9",
                   "--bands", "633", "--json")
    assert len(out["skins"]) == 20
    assert all(s["params"]["oxygenation"] == pytest.approx(0.9) for s in out["skins"])
    n0 = run_json(capsys, "spectra", "--preset", "I", "--bands", "1080", "--json")["skins"][0]
    n80 = run_json(capsys, "spectra", "--preset", "I", "--bands", "1080", "--incidence-deg", "80",
                   "--json")["skins"][0]
    assert n80["reflectance"][0] > n0["reflectance"][0]  # more surface reflection at grazing incidence


def test_spectra_sample_matches_library_sampling(capsys):
    out = run_json(capsys, "spectra", "--sample", "5", "--seed", "0", "--bands", "544", "--json")
    skins, _ = tissue.sample(5, 0)
    assert [s["params"]["melanosome"] for s in out["skins"]] == pytest.approx(skins.melanosome.tolist())


@pytest.mark.slow
def test_spectra_plot_writes_png(tmp_path, capsys):
    png = tmp_path / "p.png"
    assert main(["spectra", "--all-presets", "--plot", str(png)]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert [p.name for p in tmp_path.iterdir()] == ["p.png"]  # no temporary left behind
    assert png.stat().st_mode & 0o044  # readable by others, like any file the user writes (umask 022)


@pytest.mark.parametrize("args,msg", [
    (["--param", "oxygenation=1.5"], "oxygenation must lie in [0, 1]"),
    (["--param", "melanin=0.1"], "unknown parameter 'melanin'"),
    (["--wavelengths", "300:800:10"], "wavelengths must lie in [400, 1700] nm"),
    (["--wavelengths", "400-800"], "START:STOP:STEP"),
    (["--preset", "VII"], "unknown preset"),
    (["--incidence-deg", "95"], "--incidence-deg must lie in [0, 90)"),
])
def test_spectra_bad_input(capsys, args, msg):
    assert main(["spectra", *args]) == 2
    assert msg in capsys.readouterr().err


def test_plot_into_missing_folder_fails_cleanly(tmp_path, capsys):
    assert main(["spectra", "--preset", "I", "--plot", str(tmp_path / "nope" / "p.png")]) == 2
    assert "does not exist" in capsys.readouterr().err


@pytest.mark.slow
def test_console_script_runs_bench_json():
    r = subprocess.run([sys.executable, "-m", "torchskin.cli", "bench", "--only", "km", "--json"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    km = json.loads(r.stdout)["km"]
    assert km["samples_x_bands_per_s"] > 0 and km["device"] == "cpu" and km["dtype"] == "float32"


@pytest.mark.slow
def test_render_compile_without_a_compiler_warns_once_in_one_line(tmp_path):
    import os

    from torchskin.render.meshes import sphere_mesh, write_obj

    v, f = sphere_mesh(0.3, 2)
    write_obj(tmp_path / "ball.obj", v + [0.0, 0.0, 1.0], f)
    env = {**os.environ, "CXX": str(tmp_path / "no-such-compiler")}
    r = subprocess.run([sys.executable, "-m", "torchskin.cli", "render", "--mesh", str(tmp_path / "ball.obj"),
                        "--width", "32", "--height", "32", "--compile", "--out", str(tmp_path / "frame")],
                       capture_output=True, text=True, env=env, timeout=300)
    assert r.returncode == 0, r.stderr
    lines = [x for x in r.stderr.splitlines() if x.startswith("torchskin render: warning")]
    assert lines == ["torchskin render: warning: running compiled kernels eagerly on cpu: no C++ compiler (install g++)"]
    assert "Traceback" not in r.stderr and "RuntimeWarning" not in r.stderr
    assert (tmp_path / "frame" / "reflectance.npy").is_file()


def test_light_command_tabulates_the_light_model(capsys):
    """`torchskin light --json` is the light model's own tables (render.light.light_tables): diffuse over direct
    horizontal irradiance per band and zenith; one-line errors for a sun on the horizon or an unknown model."""
    import torch

    from torchskin.cli import main
    from torchskin.render.light import light_tables
    from torchskin.render.scene import Sun

    assert main(["light", "--zenith", "10,75", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    t = light_tables("spectrl2", [Sun(zenith_deg=10.0), Sun(zenith_deg=75.0)], [[544, 0], [633, 0], [1080, 0], [1580, 0]])
    torch.testing.assert_close(torch.tensor(doc["diffuse_over_direct"], dtype=torch.float64),
                               t.diffuse_horizontal / t.direct_horizontal)
    assert doc["model"] == "spectrl2" and doc["unit"] == "W m^-2 nm^-1" and doc["zenith_deg"] == [10.0, 75.0]
    for argv, what in ((["light", "--zenith", "90"], "--zenith"), (["light", "--illumination", "lamp"], "--illumination"),
                       (["light", "--water", "-1"], "--water")):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and what in err[0]


@pytest.mark.slow
def test_render_json_reports_the_illumination(tmp_path):
    """`torchskin render --json` names the light model and its per-band direct and diffuse horizontal irradiance;
    `--illumination thesis` renders under the thesis's lamp."""
    from torchskin.render.meshes import sphere_mesh, write_obj

    v, f = sphere_mesh(0.3, 2)
    write_obj(tmp_path / "ball.obj", v + [0.0, 0.0, 1.0], f)
    out = {}
    for model in ("spectrl2", "thesis"):
        r = subprocess.run([sys.executable, "-m", "torchskin.cli", "render", "--mesh", str(tmp_path / "ball.obj"),
                            "--width", "32", "--height", "32", "--illumination", model, "--json",
                            "--out", str(tmp_path / model)], capture_output=True, text=True, timeout=300)
        assert r.returncode == 0, r.stderr
        out[model] = json.loads(r.stdout)["illumination"]
    s, t = out["spectrl2"], out["thesis"]
    assert s["model"] == "spectrl2" and t["model"] == "thesis" and s["bands_nm"] == [544.0, 633.0, 1080.0, 1580.0]
    assert len(s["direct_horizontal"][0]) == 4 and len(s["diffuse_horizontal"][0]) == 4
    # the clear sky is blue: its diffuse share falls from 544 to 1580 nm; the thesis's grey sky is 0.1 everywhere
    share = [d / b for d, b in zip(s["diffuse_horizontal"][0], s["direct_horizontal"][0])]
    assert share == sorted(share, reverse=True) and share[0] > 3 * share[-1]
    cz = math.cos(math.radians(45.0))
    for d, b in zip(t["diffuse_horizontal"][0], t["direct_horizontal"][0]):
        assert d / (b / cz) == pytest.approx(0.1, rel=1e-5)
