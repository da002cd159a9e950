"""Measured band response curves (``Band.from_response``, ``BandSet.from_csv``): a camera's filter table wherever
bands are taken (render, generate, detect's band synthesis), and its hostile inputs."""

import json

import numpy as np
import pytest
import torch

from torchskin.bands import FWHM_TO_SIGMA, SUPPORT_FWHM, Band, BandSet, band_integrate, band_sampling, response_matrix
from torchskin.cli import main

GAUSSIANS = [(550.0, 30.0), (1080.0, 40.0)]


def gaussian_table(path, bands=GAUSSIANS, step=0.5):
    """A response table (CSV) sampling each Gaussian band over its support (centre +- SUPPORT_FWHM FWHM), zero
    beyond, on one grid for all."""
    lo = min(c - SUPPORT_FWHM * f for c, f in bands) - 10
    hi = max(c + SUPPORT_FWHM * f for c, f in bands) + 10
    wl = np.arange(lo, hi + step / 2, step)
    cols = []
    for c, f in bands:
        g = np.exp(-0.5 * ((wl - c) / (f * FWHM_TO_SIGMA)) ** 2)
        g[np.abs(wl - c) > SUPPORT_FWHM * f + 1e-9] = 0.0
        cols.append(3.7 * g)  # any scale
    rows = ["wavelength_nm," + ",".join(f"band{k}" for k in range(len(bands)))]
    rows += [",".join(f"{x:.6g}" for x in (w, *(col[i] for col in cols))) for i, w in enumerate(wl)]
    path.write_text("\n".join(rows) + "\n")
    return path


def smooth(lam):
    return 0.4 + 0.2 * np.sin(lam / 37.0) + 1e-4 * (lam - 900.0)


def test_a_table_of_a_gaussian_band_is_that_band(tmp_path):
    """Centroid and FWHM of a sampled Gaussian are its centre and FWHM, and the band value of a smooth spectrum
    through the table equals the Gaussian band's, within the error of interpolating the curve linearly between
    samples 0.5 nm apart (h^2/8 max|g''| of a peak-1 Gaussian: 1/(8 sigma^2) h^2, relative to the band's mean)."""
    bs = BandSet.from_csv(gaussian_table(tmp_path / "g.csv"))
    for b, (c, f) in zip(bs, GAUSSIANS):
        assert b.response is not None and max(b.response[1]) == 1.0
        assert abs(b.center_nm - c) <= 0.01 and abs(b.fwhm_nm - f) <= 0.05
    grid = torch.arange(400.0, 1700.0 + 1e-9, 0.05, dtype=torch.float64)
    spec = torch.as_tensor(smooth(grid.numpy()))
    got = band_integrate(spec, grid, list(bs))
    ref = band_integrate(spec, grid, [Band(c, f) for c, f in GAUSSIANS])
    for k, (_c, f) in enumerate(GAUSSIANS):
        sigma = f * FWHM_TO_SIGMA
        tol = 0.5 ** 2 / 8 / sigma ** 2 * float(spec.abs().max()) * 4 + 1e-9
        assert abs(float(got[k] - ref[k])) <= tol, (k, float(got[k] - ref[k]), tol)


def test_a_response_curve_averages_a_linear_spectrum_to_its_value_at_the_centroid():
    """For a + b lambda, any band's mean is a + b times its weights' centroid: a triangle from 600 to 640 nm,
    peaking at 610, has its centroid at (600 + 610 + 640) / 3 nm."""
    b = Band.from_response([590, 600, 610, 640, 650], [0, 0, 2.0, 0, 0])
    assert b.center_nm == pytest.approx((600 + 610 + 640) / 3, abs=0.005)
    assert b.fwhm_nm == pytest.approx(20.0) and b.support == (600.0, 640.0)
    grid, W = band_sampling([b], step_nm=0.25, dtype=torch.float64)
    val = float((3.0 + 0.01 * grid) @ W[:, 0])
    assert val == pytest.approx(3.0 + 0.01 * (600 + 610 + 640) / 3, abs=1e-6)


def test_a_response_band_round_trips_through_json_scene_and_config(tmp_path):
    from torchskin.bands import scene_bands
    from torchskin.dataset.config import config_bands, resolve_config
    from torchskin.render.scene import Scene, default_scene

    path = gaussian_table(tmp_path / "cam.csv")
    bs = BandSet.parse(str(path))
    assert BandSet.from_json(bs.to_json()) == bs and BandSet.parse(bs.to_json()) == bs
    sc = default_scene()
    sc.bands = scene_bands(bs)
    back = Scene.from_json(sc.to_json())
    assert back.band_list == bs.bands
    cfg = resolve_config({"bands": {"spec": str(path)}})
    path.unlink()  # the configuration (a dataset's manifest) keeps the curves, not the path
    assert config_bands(cfg) == bs and cfg["bands"]["spec"].startswith("[")


def test_rendering_through_a_table_of_gaussians_equals_rendering_the_gaussians(tmp_path):
    """The same filters given as centre/FWHM and as a response table give the same frame, within the table's
    interpolation error (relative 1e-3 of each band's largest reflectance)."""
    from torchskin.bands import scene_bands
    from torchskin.render.pipeline import render
    from torchskin.render.scene import Camera, MeshSpec, default_scene
    from torchskin.render.sensor import Sensor

    frames = []
    cylinder = MeshSpec("subject", "cylinder", "skin", {"radius": 0.2, "height": 1.6, "segments": 24})
    for bands in (BandSet.of(GAUSSIANS), BandSet.from_csv(gaussian_table(tmp_path / "cam.csv"))):
        sc = default_scene(subject=cylinder, camera=Camera(width=32, height=32))
        sc.bands = scene_bands(bands)
        frames.append(render(sc, sensor=Sensor(noise=False), sky_view="rays").reflectance)
    a, b = frames
    scale = a.abs().amax(dim=(0, 1, 2, 3))
    assert float(((a - b).abs().amax(dim=(0, 1, 2, 3)) / scale).max()) <= 1e-3


def test_detect_synthesises_a_response_band_from_a_hyperspectral_cube():
    """A 1 nm cube of a smooth spectrum, synthesised to a response-curve band (``band_plan``), equals the band's
    response applied to the spectrum on a 0.01 nm grid, within linear interpolation between 1 nm samples and
    float32 rounding."""
    from torchskin.onboard import apply_plan, band_plan

    b = Band.from_response([590, 600, 610, 640, 650], [0, 0, 1.0, 0, 0])
    lam = np.arange(500.0, 700.0 + 0.5, 1.0)
    cube = np.broadcast_to(smooth(lam).astype(np.float32)[:, None, None], (len(lam), 2, 3)).copy()
    plan = band_plan(lam.tolist(), None, [b])
    assert plan["kind"] == "synthesis"
    got = apply_plan(plan, cube)[0, 0, 0]
    fine = torch.arange(500.0, 700.0 + 1e-9, 0.01, dtype=torch.float64)
    ref = float(torch.as_tensor(smooth(fine.numpy())) @ response_matrix(fine, [b])[:, 0])
    s2 = 0.2 / 37.0 ** 2  # max |S''|
    assert abs(float(got) - ref) <= 1.0 ** 2 / 8 * s2 * 2 + 1e-6


def run(*argv: str) -> int:
    try:
        return main(list(argv))
    except SystemExit as e:  # an argparse refusal
        return int(e.code or 0)


BAD_TABLES = {
    "nan": ("wavelength_nm,a\n500,0\n510,nan\n520,0\n", "values must be finite and >= 0"),
    "negative": ("wavelength_nm,a\n500,0\n510,1\n520,-0.1\n", "values must be finite and >= 0"),
    "unsorted": ("wavelength_nm,a\n500,0\n520,1\n510,0\n", "must strictly increase"),
    "zero": ("wavelength_nm,a\n500,0\n510,0\n520,0\n", "every value is zero"),
    "text": ("wavelength_nm,a\n500,0\n510,high\n520,0\n", "non-number"),
    "ragged": ("wavelength_nm,a,b\n500,0,0\n510,1\n520,0,0\n", "line 3 has 2 values"),
    "outside": ("wavelength_nm,a\n1690,0\n1700,1\n1750,0\n", "outside the model's 400-1700 nm"),
    "micrometres": ("wavelength_nm,a\n0.5,0\n0.55,1\n0.6,0\n", "wavelengths in µm?"),
    "unsorted bands": ("wavelength_nm,a,b\n500,0,0\n600,0,1\n700,1,0\n800,0,0\n", "strictly ascending"),
}


@pytest.mark.parametrize("command", ["render", "generate"])
@pytest.mark.parametrize("case", list(BAD_TABLES))
def test_a_bad_response_table_is_refused_in_one_line_with_nothing_written(tmp_path, capsys, command, case):
    text, needle = BAD_TABLES[case]
    table = tmp_path / "cam.csv"
    table.write_text(text)
    out = tmp_path / "out"
    args = (["render", "--width", "8", "--height", "8"] if command == "render" else ["generate", "--configs", "8"])
    rc = run(*args, "--bands", str(table), "--out", str(out))
    err = capsys.readouterr().err.strip()
    assert rc == 2 and needle in err and "\n" not in err and "--bands" in err, err
    assert not out.exists()


def test_a_missing_response_table_is_named(tmp_path, capsys):
    rc = run("render", "--bands", str(tmp_path / "none.csv"), "--out", str(tmp_path / "o"))
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "none.csv" in err and "cannot read it" in err and "\n" not in err


def test_the_rededge_mx_preset_names_its_five_bands():
    b = BandSet.parse("rededge-mx")
    assert [(x.center_nm, x.fwhm_nm) for x in b] == [(475, 32), (560, 27), (668, 14), (717, 12), (842, 57)]
    assert json.loads(b.to_json())[0] == {"center_nm": 475.0, "fwhm_nm": 32.0}


def test_a_cube_lacking_model_bands_is_told_which_before_any_gap():
    """A silicon camera's cube (475..842 nm) for the index-band model: the bands it lacks (1080 and 1580 nm) are
    named, not the wide gap it leaves around 544 nm."""
    from torchskin.onboard import band_plan

    with pytest.raises(ValueError, match="does not cover the model's 1080 nm band .*, nor its 1580 nm band$"):
        band_plan([475, 560, 668, 717, 842], None, [544, 633, 1080, 1580])
    with pytest.raises(ValueError, match="gap inside the model's 544 nm band"):  # spanned, but too sparsely
        band_plan([475, 560, 668, 717, 842, 1100, 1600], None, [544, 633, 1080, 1580])


def test_a_wide_band_sees_a_materials_spectrum_averaged_over_its_response():
    """A material's spectrum given at wavelengths: a monochromatic band reads it at its centre (as before, bit for
    bit), a constant spectrum stays that constant under any band, and a step inside a wide band's response reads
    between its two levels, falling from the high level to the low as the step moves up through the band (the
    centre alone would read one level or the other)."""
    import torch

    from torchskin.bands import at_wavelengths, per_band
    from torchskin.render.materials import band_reflectance, spectral_context
    from torchskin.render.scene import Sun

    suns = [Sun(zenith_deg=30.0)]
    mono = [Band(544.0), Band(633.0), Band(1080.0), Band(1580.0)]
    spec = at_wavelengths([0.12, 0.34, 0.2, 0.41, 0.05], [500.0, 600.0, 900.0, 1300.0, 1650.0])
    sp = spectral_context(mono, suns, "spectrl2")
    assert band_reflectance(spec, sp, "r").tolist() == per_band(spec, mono, "r")
    wide = [Band(560.0, 27.0), Band(1080.0, 40.0)]
    sp = spectral_context(wide, suns, "spectrl2")
    assert torch.allclose(band_reflectance(at_wavelengths([0.3, 0.3], [400.0, 1700.0]), sp, "r"),
                          torch.full((2,), 0.3, dtype=torch.float64), rtol=0, atol=1e-15)
    reads = []
    for edge in (1010.0, 1050.0, 1070.0, 1090.0, 1110.0, 1150.0):  # 0.6 below the edge, 0.1 above
        step = at_wavelengths([0.6, 0.6, 0.1, 0.1], [400.0, edge - 0.5, edge + 0.5, 1700.0])
        reads.append(float(band_reflectance(step, sp, "r")[1]))
    assert abs(reads[0] - 0.1) < 1e-3 and abs(reads[-1] - 0.6) < 1e-3  # the step outside the response
    assert all(a < b for a, b in zip(reads, reads[1:]))  # rises as the step moves up through the band
    assert 0.2 < reads[2] < 0.5 and 0.2 < reads[3] < 0.5
