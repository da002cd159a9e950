"""Issue 12 part A: hostile input that used to give silently wrong science or unbounded allocation.

Each test reproduces the original failure (in its docstring) and asserts the fix.
"""

import math

import pytest
import torch

from torchskin import fit, optics, tissue
from torchskin.bands import MAX_GRID_POINTS, Band, band_sampling, parse_bands
from torchskin.cli import main
from torchskin.dataset.config import load_config, resolve_config

DT = torch.float64


def _one_error_line(capsys, command: str) -> str:
    """The bad-input contract's stderr (one line naming what is wrong) and stdout (nothing) of the last run."""
    out, err = capsys.readouterr()
    assert out == "", out
    assert err.startswith(f"torchskin {command}: error: ") and err.count("\n") == 1, err
    assert "Traceback" not in err
    return err


# ------------------------------------------------------------------------ 1. allocation before validation
def test_band_sampling_refuses_a_band_outside_the_model_before_allocating():
    """Was: band 544/1e9 built a ~3e9-point linspace and was OOM-killed."""
    with pytest.raises(ValueError, match=r"band 544/1e\+09 nm.*outside the model's 400-1700 nm.*at most 96 nm"):
        band_sampling([Band(544.0, 1e9)])
    with pytest.raises(ValueError, match=r"bad band '544/1e9' in --bands"):
        parse_bands("544,544/1e9")
    with pytest.raises(ValueError, match="centre lies outside"):
        band_sampling([Band(300.0)])
    with pytest.raises(ValueError, match="1690/20 nm.*1660..1720"):
        band_sampling([Band(1690.0, 20.0)])


def test_band_sampling_caps_grid_points_and_checks_the_step():
    with pytest.raises(ValueError, match=f"at most {MAX_GRID_POINTS}"):
        band_sampling([Band(1000.0, 400.0)], step_nm=1e-6)  # 6e8 points
    for step in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="step_nm must be a positive finite"):
            band_sampling([Band(1000.0, 40.0)], step_nm=step)
    # a legitimate Gaussian band still samples and averages correctly: a linear spectrum's band value is
    # its value at the (symmetric) band centre
    grid, W = band_sampling([Band(1000.0, 40.0), Band(544.0)], dtype=DT)
    torch.testing.assert_close((2.0 * grid + 1.0) @ W, torch.tensor([2001.0, 1089.0], dtype=DT))


def test_wavelength_grid_refuses_too_many_points_before_allocating():
    """Was: 400:1700:1e-9 tried to allocate 1.3e12 wavelengths."""
    with pytest.raises(ValueError, match=r"1.3e\+12 points; at most 1000000"):
        tissue.wavelength_grid(400, 1700, 1e-9)
    with pytest.raises(ValueError, match="step must be a finite"):
        tissue.wavelength_grid(400, 1700, float("nan"))
    with pytest.raises(ValueError, match="stop must be a finite"):
        tissue.wavelength_grid(400, float("inf"), 1)
    assert tissue.wavelength_grid(400, 1700, 0.01).numel() == 130_001  # fine grids below the cap still work
    assert tissue.wavelength_grid(400, 1700, 5).numel() == 261


@pytest.mark.parametrize("argv", [
    ["spectra", "--bands", "544/1e9"],
    ["spectra", "--wavelengths", "400:1700:1e-9"],
    ["render", "--bands", "544/1e9"],
])
def test_cli_refuses_huge_sampling_with_one_line(argv, capsys, tmp_path):
    extra = ["--out", str(tmp_path / "frame")] if argv[0] == "render" else []
    assert main(argv + extra) == 2
    err = _one_error_line(capsys, argv[0])
    assert ("--bands" in err) if "--bands" in argv else ("at most 1000000" in err)
    assert not (tmp_path / "frame").exists()


# ------------------------------------------------------------------------------- 2. fit identifiability
@pytest.mark.slow
def test_fit_at_one_wavelength_leaves_every_parameter_undetermined():
    """Was: 550 nm alone reported oxygenation 0.70 +- 5e-5 (truth 0.50) as determined."""
    wl = torch.tensor([550.0], dtype=DT)
    R = tissue.total_reflectance(tissue.preset("I-II", dtype=DT), wl)[None]
    res = fit.fit_skin(R, wl, lut_size=500)
    assert not bool(res.identifiable.any())
    assert bool(torch.isinf(res.std).all())  # in the Jacobian's null space, not a tiny Fisher uncertainty
    assert all(v is None for v in res.reported()[0].values())
    # fewer wavelengths than the six parameters can never determine them all
    wl4 = torch.tensor([544.0, 633.0, 1080.0, 1580.0], dtype=DT)
    res4 = fit.fit_skin(tissue.total_reflectance(tissue.preset(["I-II", "V-VI"], dtype=DT), wl4), wl4,
                        lut_size=500)
    assert not bool(res4.identifiable.all(1).any())
    assert bool(torch.isinf(res4.std).any(1).all())


def test_fisher_std_uses_the_rank_of_the_jacobian():
    scale = torch.ones(3, dtype=DT)
    sigma = torch.ones(1, dtype=DT)
    # parameter 2 has no effect: it alone is undetermined; the others have std sigma / |dR/dp|
    J = torch.tensor([[[2.0, 0.0, 0.0], [0.0, 4.0, 0.0]]], dtype=DT)
    std = fit.fisher_std(J, sigma, scale)
    torch.testing.assert_close(std[0, :2], torch.tensor([0.5, 0.25], dtype=DT))
    assert math.isinf(float(std[0, 2]))
    # parameters 0 and 1 act identically (confounded): both undetermined, parameter 2 determined
    J = torch.tensor([[[1.0, 1.0, 0.0], [2.0, 2.0, 0.0], [0.0, 0.0, 3.0]]], dtype=DT)
    std = fit.fisher_std(J, sigma, scale)
    assert bool(torch.isinf(std[0, :2]).all()) and float(std[0, 2]) == pytest.approx(1 / 3)
    # a non-finite Jacobian gives NaN, not an exception
    J = torch.tensor([[[float("nan"), 1.0, 0.0]]], dtype=DT)
    assert bool(torch.isnan(fit.fisher_std(J, sigma, scale)).all())


@pytest.mark.slow
def test_degenerate_spectrum_is_not_converged_and_does_not_stop_the_others():
    """Was: a constant 0.999 (or 0 / 1) spectrum raised LinAlgError for the whole batch."""
    wl = tissue.wavelength_grid(450, 1650, 100, dtype=DT)
    good = tissue.total_reflectance(tissue.preset("III", dtype=DT), wl)
    R = torch.stack([torch.full_like(good, 0.999), good])
    res = fit.fit_skin(R, wl, lut_size=500)
    assert not bool(res.converged[0]) and not bool(res.identifiable[0].any())
    assert float(res.rmse[1]) < 0.003
    for c in (0.0, 1.0):
        with pytest.raises(ValueError, match="row 1: every reflectance is 0 or 1"):
            fit.fit_skin(torch.stack([good, torch.full_like(good, c)]), wl)


# --------------------------------------------------------------------------------------------- 3. float16
@pytest.mark.parametrize("half,tol", [(torch.float16, 1e-3), (torch.bfloat16, 5e-3)])
def test_half_precision_matches_float32(half, tol):
    """Was: float16 gave 0.38-0.40 for the I-II preset at 544 nm where float32 gives 0.30."""
    wl = torch.tensor([544.0, 633.0, 1080.0, 1580.0])
    skins = tissue.preset(list(tissue.PRESETS))
    ref = {
        "reflectance": tissue.reflectance(skins, wl),
        "total": tissue.total_reflectance(skins, wl),
        "subsurface": tissue.subsurface_reflectance(skins, wl),
        "diffuse": tissue.diffuse_reflectance(skins, wl, theta_i=0.5),
    }
    h, wh = skins.to(dtype=half), wl.to(half)
    got = {
        "reflectance": tissue.reflectance(h, wh),
        "total": tissue.total_reflectance(h, wh),
        "subsurface": tissue.subsurface_reflectance(h, wh),
        "diffuse": tissue.diffuse_reflectance(h, wh, theta_i=0.5),
    }
    for k in ref:
        assert got[k].dtype == half, k
        assert float((got[k].float() - ref[k]).abs().max()) <= tol, k
    assert float(got["reflectance"][list(tissue.PRESETS).index("I-II"), 0]) == pytest.approx(0.303, abs=1e-3)


# ---------------------------------------------------------------------------------------------- 4. angles
@pytest.mark.parametrize("fn", [tissue.reflectance, tissue.diffuse_reflectance])
def test_incidence_outside_the_hemisphere_is_refused(fn):
    """Was: theta_i = 2.5 rad gave a reflectance of -1.99."""
    p, wl = tissue.preset("I-II", dtype=DT), torch.tensor([544.0, 1080.0], dtype=DT)
    for bad in (2.5, -0.1, float("nan")):
        with pytest.raises(ValueError, match="theta_i must lie in"):
            fn(p, wl, theta_i=bad)
    with pytest.raises(ValueError, match="rho0 must lie in"):
        fn(p, wl, rho0=1.5)
    # grazing incidence itself is allowed (also as a float32 pi/2, which rounds above pi/2) and physical
    for th in (math.pi / 2, torch.tensor(math.pi / 2, dtype=torch.float32)):
        r = fn(p, wl, theta_i=th)
        assert bool(((r >= 0) & (r <= 1 + 1e-12)).all())


def test_brdf_parameters_are_validated_in_the_public_functions():
    """Was: a negative rho_d gave a negative BRDF, sigma2 = 0 gave NaN."""
    args = (0.1, 0.2, math.pi)
    with pytest.raises(ValueError, match="rho_d must lie in"):
        optics.combined_brdf(*args, -0.5, 0.03, 0.04)
    for s2 in (0.0, -0.01, float("inf"), float("nan")):
        with pytest.raises(ValueError, match=r"sigma2 must lie in \(0, inf\)"):
            optics.microfacet_brdf(*args, s2, 0.04)
        with pytest.raises(ValueError, match="sigma2"):
            optics.combined_brdf(*args, 0.5, torch.tensor([0.03, s2]), 0.04)
    with pytest.raises(ValueError, match=r"rho0 must lie in \[0, 1\)"):
        optics.microfacet_brdf(*args, 0.03, 1.0)
    with pytest.raises(ValueError, match="r_sub must lie in"):
        optics.skin_brdf(*args, 1.5, 0.03, 0.04)
    with pytest.raises(ValueError, match="theta_i must lie in"):
        optics.dhr(lambda a, b, c: optics.combined_brdf(a, b, c, 0.5, 0.03, 0.04), torch.tensor([2.0]))
    # the cosine kernels (the renderer's per-frame path) check Python numbers only: no device round trip
    one = torch.ones(())
    with pytest.raises(ValueError, match="sigma2"):
        optics.microfacet_brdf_cos(one, one, one, 0.0, 0.04)
    f = optics.combined_brdf_cos(one, one, one, torch.tensor(0.5), torch.tensor(0.03), torch.tensor(0.04))
    assert float(f) == pytest.approx(float(optics.combined_brdf(0.0, 0.0, math.pi, 0.5, 0.03, 0.04)))


# ------------------------------------------------------------------------------------------ 5. config NaN
@pytest.mark.parametrize("section,key,value", [
    ("sun", "zenith_deg", [0.0, float("nan")]),
    ("light", "aerosol_500nm", [float("nan"), 0.1]),
    ("camera", "subject_fraction", float("nan")),
    ("camera", "range_m", [5.0, float("inf")]),
    ("atmosphere", "transmittance", [float("-inf"), 1.0]),
])
def test_config_refuses_non_finite_numbers(section, key, value):
    """Was: [0, nan] passed validation and wrote NaN into the manifest."""
    with pytest.raises(ValueError, match=rf"{section}\.{key} must hold finite numbers"):
        resolve_config({section: {key: value}})


def test_config_file_with_nan_is_refused(tmp_path):
    p = tmp_path / "c.toml"
    p.write_text("[sun]\nzenith_deg = [0.0, nan]\n")
    with pytest.raises(ValueError, match=r"sun\.zenith_deg must hold finite numbers"):
        load_config(p)


# ------------------------------------------------------------------------------------------- 6. CSV input
_WL = [450, 550, 650, 850, 1080, 1300, 1580]


def _row(vals):
    return ",".join(f"{v:g}" for v in vals)


@pytest.mark.parametrize("text,msg", [
    ("a,b,c\n1,2,3\n", "spectra.csv: the header must hold wavelengths in nm; column 0 is 'b'"),
    ("name\ns0\n", "spectra.csv: the header holds no wavelength columns"),
    ("300," + _row(_WL[1:]) + "\n" + _row([0.3] * 7) + "\n", "spectra.csv: column 0: wavelength 300 nm"),
    ("1800," + _row(_WL[1:]) + "\n" + _row([0.3] * 7) + "\n", "spectra.csv: column 0: wavelength 1800 nm"),
    ("nan," + _row(_WL[1:]) + "\n" + _row([0.3] * 7) + "\n", "spectra.csv: column 0: wavelength nan nm"),
    (_row(_WL) + "\n0.3,,0.3,0.3,0.3,0.3,0.3\n", r"spectra.csv: row 0, column 1: '' is not a number"),
    (_row(_WL) + "\n0.3,0.3,x,0.3,0.3,0.3,0.3\n", r"spectra.csv: row 0, column 2: 'x' is not a number"),
    (_row(_WL) + "\n0.3,0.3\n", "spectra.csv: row 0 has 2 values for 7 columns"),
    (_row(_WL) + "\n" + _row([0.3] * 7) + "\n" + _row([0] * 7) + "\n", "spectra.csv: row 1: every reflectance is 0"),
    (_row(_WL) + "\n" + _row([1] * 7) + "\n", "spectra.csv: row 0: every reflectance is 0 or 1"),
    (_row(_WL) + "\n" + _row([0.3] * 6 + [1.5]) + "\n", r"spectra.csv: row 0, column 6 \(1580 nm\)"),
    (_row(_WL) + "\n", "spectra.csv: needs a header row"),
])
def test_spectra_csv_errors_name_the_file(tmp_path, text, msg):
    p = tmp_path / "spectra.csv"
    p.write_text(text)
    with pytest.raises(ValueError, match=msg):
        fit.read_spectra_csv(p)


def test_spectra_csv_not_text(tmp_path):
    p = tmp_path / "spectra.csv"
    p.write_bytes(b"\xff\xfe\x00\x81\x90" * 10)
    with pytest.raises(ValueError, match="spectra.csv: not a readable CSV"):
        fit.read_spectra_csv(p)


@pytest.mark.parametrize("body,msg", [
    ("theta_i_deg,theta_r_deg,delta_phi_deg,green\n0,0,180,0.1\n", "column 3 is 'green'"),
    ("theta_i_deg,theta_r_deg,delta_phi_deg,nan\n0,0,180,0.1\n", "column 3 is 'nan'"),
    ("theta_i_deg,theta_r_deg,delta_phi_deg,544\n100,0,180,0.1\n", r"row 0, column 0 \(theta_i_deg\): 100"),
    ("theta_i_deg,theta_r_deg,delta_phi_deg,544\n0,0,180,0.1\n0,10,nan,0.1\n", r"row 1, column 2 \(delta_phi"),
    ("theta_i_deg,theta_r_deg,delta_phi_deg,544\n0,0,180,-0.1\n", r"row 0, column 3 \(544 nm\): BRDF value -0.1"),
    ("theta_i_deg,theta_r_deg,delta_phi_deg,544\n0,0,180,0\n0,10,180,0\n", "every BRDF value is 0"),
    ("theta_i_deg,theta_r_deg,delta_phi_deg,544\n", "no data rows"),
])
def test_brdf_csv_errors_name_the_file(tmp_path, body, msg):
    p = tmp_path / "brdf.csv"
    p.write_text(body)
    with pytest.raises(ValueError, match="brdf.csv: .*" + msg):
        fit.read_brdf_csv(p)


@pytest.mark.slow
def test_cli_fit_skin_one_wavelength_and_dark_spectra(tmp_path, capsys):
    """Was: a one-wavelength CSV reported parameters as determined; a dark spectrum ended in LinAlgError."""
    out = tmp_path / "params.csv"
    one = tmp_path / "one.csv"
    one.write_text("name,550\ns0,0.35\n")
    assert main(["fit-skin", str(one), "--out", str(out)]) == 0  # fitted, and every parameter left undetermined
    text = capsys.readouterr().out
    assert "not determined by these data (left empty): melanosome, blood, oxygenation" in text
    row = out.read_text().splitlines()[1].split(",")
    assert row[0] == "s0" and row[1:7] == [""] * 6
    out.unlink()
    dark = tmp_path / "dark.csv"
    dark.write_text("name," + _row(_WL) + "\ns0," + _row([0] * 7) + "\n")
    assert main(["fit-skin", str(dark), "--out", str(out)]) == 2
    assert "dark.csv: row 0: every reflectance is 0 or 1" in _one_error_line(capsys, "fit-skin")
    assert not out.exists()


def test_config_names_where_the_sky_fraction_went():
    """sun.sky_fraction left the config with the light stage: an old config gets one line saying where it went."""
    from torchskin.dataset.config import resolve_config

    with pytest.raises(ValueError, match=r"sun\.sky_fraction has moved.*light\.sky_fraction"):
        resolve_config({"sun": {"sky_fraction": [0.0, 0.2]}})


@pytest.mark.parametrize("text,what", [("1580,1080,633,544", "ascending"), ("544,544", "ascending"),
                                        ("544,,633", "empty item"), ("544,544.0001,633", "both written as 544 nm")])
def test_bands_out_of_order_or_repeated_are_refused(text, what):
    """Four per-band values (material spectra, sensor settings) are read in band order: a reversed band list
    put the ground's 1580 nm reflectance on 544 nm; a repeated band overwrote its own image. Both are refused,
    at the CLI and in a Scene. Two centres that differ beyond the sixth significant digit wrote one
    ``band_544nm.png`` over the other: refused too."""
    from torchskin.bands import parse_bands
    from torchskin.render.scene import default_scene

    with pytest.raises(ValueError, match=what):
        parse_bands(text)
    sc = default_scene(subject="file", mesh_path="unused.obj")
    sc.bands = [[1580.0, 0.0], [544.0, 0.0]]
    with pytest.raises(ValueError, match="ascending"):
        sc.__post_init__()


def test_a_range_key_given_one_number_names_the_key():
    """Was: `[light] aerosol_500nm = 0.1` failed later with "unexpected TypeError"."""
    from torchskin.dataset.config import resolve_config

    for section, key in (("light", "aerosol_500nm"), ("sun", "zenith_deg")):
        with pytest.raises(ValueError, match=rf"{section}\.{key} must be \[min, max\]"):
            resolve_config({section: {key: 0.1}})


def test_day_of_year_stays_inside_its_range():
    from torchskin.dataset.config import resolve_config, sample_group

    with pytest.raises(ValueError, match=r"light\.day_of_year must hold a whole day"):
        resolve_config({"light": {"day_of_year": [1.2, 1.4]}})  # was: accepted, every row day 1, outside it
    days = {sample_group(resolve_config({"light": {"day_of_year": [99.6, 100.4]}}), 0, i).light["day_of_year"]
            for i in range(8)}
    assert days == {100}
