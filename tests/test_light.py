"""The light stage against pvlib and closed-form radiometry.

Expected values are computed here, independently of ``torchskin.render.light``: SPECTRL2 spectra straight from
``pvlib.spectrum.spectrl2`` (the package's documented inputs: the default ``Atmosphere``, Kasten 1966 air mass),
Hay-Davies and plane-of-array irradiance from ``pvlib.irradiance``, view factors from their closed forms (Howell's
catalogue, configuration B-3, and (1 ± cos β)/2 for a tilted plane), the thesis lamp from Planck's law.

Geometry conventions (``render.scene``): z up; azimuth from +x towards +y, so ``Sun(zenith_deg=z)`` shines from the
+x side, direction (sin z, 0, cos z); a "plane" mesh is a vertical rectangle facing +x (y in ±width/2, z in
[0, height]) and ``tilt_deg`` turns its normal up: 90 is level (facing +z, covering x in [px - height, px]),
``tilt_deg = 90 - β`` gives a surface tilted β from the horizontal, facing +x; a camera at zenith 0 looks
straight down.
"""

import math

import numpy as np
import pytest
import torch
from pvlib import atmosphere as pv_atmosphere
from pvlib import irradiance as pv_irradiance
from pvlib import spectrum as pv_spectrum

from torchskin.bands import band_sampling
from torchskin.render.light import light_tables, sun_irradiance
from torchskin.render.pipeline import render
from torchskin.render.raycast import SKY_RAYS
from torchskin.render.scene import SUN_SOLID_ANGLE_SR, Atmosphere, Camera, Material, MeshSpec, Scene, Sun

CENTRES = (544.0, 633.0, 1080.0, 1580.0)
BANDS = [[c, 0.0] for c in CENTRES]
#: the reference clear sky of the published table and of ``Atmosphere()``'s defaults
CLEAR_SKY = {"aerosol_turbidity_500nm": 0.1, "precipitable_water": 1.42, "ozone": 0.344, "surface_pressure": 101325.0,
             "dayofyear": 172, "alpha": 1.14, "ground_albedo": 0.2}

# ------------------------------------------------------------------------------------------- ray-count tolerances
# A view fraction is a count of SKY_RAYS cosine-weighted hemisphere rays (a Fibonacci pattern turned by a hashed
# angle per pixel). Measured against the closed forms on the scenes of this file and on larger frames (up to
# 256 x 256, 11,664 pixels):
# - one pixel is off by at most 3.5 rays (0.109 = 3.5/32) under a partial roof, 2 rays (0.0625) for the horizon of
#   a tilted plane: PIXEL_TOL allows 4 rays;
# - the per-pixel error has a standard deviation of 0.027-0.031 (0.026-0.029 over every rotation of the pattern at
#   one point; the bound 0.5/sqrt(32) = 0.088 of independent rays is far looser): SIGMA_PX = 0.035, scaled as
#   1/sqrt(rays) should SKY_RAYS change (stratified patterns converge at least that fast);
# - the pixel mean has a systematic part: rays start SHADOW_OFFSET_M = 1 mm off the surface (a roof 0.5 m above
#   looks 0.1-0.2 % bigger: +0.8e-3 to +0.9e-3 in its view factor) and the 32-ray pattern, averaged over its
#   rotations, is a 32-point quadrature (+0.2e-3 to +0.5e-3): SYSTEMATIC = 2e-3.
# So the mean over N pixels must lie within SYSTEMATIC + 4 SIGMA_PX / sqrt(N) of the closed form (4 sigma; the
# hashed rotations make pixels independent draws). Measured mean errors here: -0.0008 for the tilted plane's sky
# and ground views (N = 484, bound 0.0084), -0.0025 to -0.0040 under the roof (N = 400, view factors 0.58-0.71,
# bound 0.0090).
PIXEL_TOL = 4.0 / SKY_RAYS
SIGMA_PX = 0.035 * math.sqrt(32.0 / SKY_RAYS)
SYSTEMATIC = 2e-3


def mean_tol(n: int) -> float:
    return SYSTEMATIC + 4.0 * SIGMA_PX / math.sqrt(n)


# --------------------------------------------------------------------------------------------- pvlib, independently
def pvlib_spectra(zenith_deg: float, airmass_model: str = "kastenyoung1989") -> dict[str, np.ndarray]:
    """SPECTRL2 on pvlib's own 122 wavelengths for one sun over a horizontal surface."""
    z = np.array([float(zenith_deg)])
    out = pv_spectrum.spectrl2(apparent_zenith=z, aoi=z, surface_tilt=0.0,
                               relative_airmass=pv_atmosphere.get_relative_airmass(z, model=airmass_model),
                               **CLEAR_SKY)
    wl = np.asarray(out["wavelength"], dtype=np.float64)
    res = {k: np.asarray(out[k], dtype=np.float64).reshape(len(wl), -1)[:, 0] for k in ("dni", "dhi", "dni_extra")}
    res["wavelength"] = wl
    return res


def at_centres(wl: np.ndarray, y: np.ndarray) -> np.ndarray:
    """A monochromatic band's value: the spectrum linearly interpolated at its centre."""
    return np.interp(np.array(CENTRES), wl, y)


def band_light(zenith_deg: float) -> dict[str, np.ndarray]:
    """Per band: DNI, DHI, DNI_extra interpolated at the centres, GHI, and Hay-Davies' isotropic sky on a horizontal
    surface and circumsolar irradiance normal to the beam (A DHI / cos θz), both by pvlib wavelength by wavelength on
    SPECTRL2's own grid and then interpolated at the centres (checked against the explicit (1 - DNI/DNI_extra) DHI)."""
    sp = pvlib_spectra(zenith_deg)
    b = {k: at_centres(sp["wavelength"], sp[k]) for k in ("dni", "dhi", "dni_extra")}
    cz = math.cos(math.radians(zenith_deg))
    b["ghi"] = b["dni"] * cz + b["dhi"]
    hd = pv_irradiance.haydavies(0.0, 180.0, sp["dhi"], sp["dni"], sp["dni_extra"], zenith_deg, 180.0,
                                 return_components=True)
    iso = np.asarray(hd["poa_isotropic"])
    np.testing.assert_allclose(iso, (1 - sp["dni"] / sp["dni_extra"]) * sp["dhi"], rtol=1e-12)
    b["iso"] = at_centres(sp["wavelength"], iso)
    b["circumsolar_normal"] = at_centres(sp["wavelength"], np.asarray(hd["poa_circumsolar"])) / cz  # Rb = 1
    return b


def nd(a, b):
    return (a - b) / (a + b)


# ------------------------------------------------------------------------------------------------------- scenes
MATS = {"grey": Material(reflectance=0.4), "white": Material(reflectance=0.9), "dark": Material(reflectance=0.05)}


def level(name: str, material: str, centre: tuple[float, float], size: tuple[float, float], z: float = 0.0) -> MeshSpec:
    """A level rectangle (normal +z) centred on ``centre`` (x, y) of ``size`` (x extent, y extent) at height z."""
    (cx, cy), (sx, sy) = centre, size
    return MeshSpec(name, "plane", material, {"width": sy, "height": sx}, position=[cx + sx / 2, cy, z], tilt_deg=90.0)


def pixels_of(res, name: str) -> torch.Tensor:
    gb = res.gbuffer
    return gb.mesh[0] == gb.mesh_names.index(name)


def test_level_plane_helper_faces_up_where_asked():
    from torchskin.render.meshes import build_mesh

    m = build_mesh(level("p", "grey", (1.0, -2.0), (0.4, 0.6), z=0.3))
    lo, hi = m.vertices.min(0), m.vertices.max(0)
    np.testing.assert_allclose([lo[0], hi[0], lo[1], hi[1], lo[2], hi[2]], [0.8, 1.2, -2.3, -1.7, 0.3, 0.3], atol=1e-6)
    np.testing.assert_allclose(m.vertex_normals, np.tile([0.0, 0.0, 1.0], (len(m.vertices), 1)), atol=1e-6)


# ------------------------------------------------------------------------------------------------- 1. SPECTRL2
#: diffuse / direct horizontal irradiance at 544, 633, 1080, 1580 nm (published, pvlib.spectrum.spectrl2 with the
#: reference clear sky), with the number of decimals printed
PUBLISHED = {10.0: ([0.159, 0.110, 0.040, 0.022], 3), 45.0: ([0.211, 0.145, 0.052, 0.029], 3),
             60.0: ([0.288, 0.194, 0.068, 0.037], 3), 75.0: ([0.567, 0.357, 0.117, 0.062], 3),
             85.0: ([2.75, 1.26, 0.300, 0.150], None)}


@pytest.mark.parametrize("zenith", [
    10.0, 45.0, 60.0, 75.0, 85.0])
def test_spectrl2_diffuse_to_direct_matches_published_table(zenith):
    """DHI / (DNI cos θz) per band, ±1 in the last printed digit."""
    assert Atmosphere() == Atmosphere(aerosol_500nm=0.1, precipitable_water_cm=1.42, ozone_atm_cm=0.344,
                                      pressure_pa=101325.0, day_of_year=172, angstrom_alpha=1.14, ground_albedo=0.2)
    t = light_tables("spectrl2", [Sun(zenith_deg=zenith)], BANDS)
    got = (t.diffuse_horizontal / t.direct_horizontal)[0].numpy()
    values, decimals = PUBLISHED[zenith]
    # the 85° row is printed to 3 significant digits: 2.75, 1.26 (0.01) then 0.300, 0.150 (0.001)
    unit = np.full(4, 10.0 ** -decimals) if decimals else np.array([0.01, 0.01, 0.001, 0.001])
    assert np.all(np.abs(got - np.array(values)) <= unit + 1e-12), (zenith, got.round(4).tolist())


@pytest.mark.parametrize("zenith", [10.0, 45.0, 60.0, 75.0, 85.0])
def test_spectrl2_tables_equal_pvlib(zenith):
    """Every table against pvlib's spectra and Hay-Davies: beam = DNI + A DHI / cos θz, sky = (1 - A) DHI (pvlib's
    isotropic term, horizontal), ground = GHI, direct_horizontal = DNI cos θz, diffuse_horizontal = DHI."""
    t = light_tables("spectrl2", [Sun(zenith_deg=zenith)], BANDS)
    b = band_light(zenith)
    cz = math.cos(math.radians(zenith))
    expected = {"beam": b["dni"] + b["circumsolar_normal"], "sky": b["iso"], "ground": b["ghi"],
                "direct_horizontal": b["dni"] * cz, "diffuse_horizontal": b["dhi"]}
    for name, want in expected.items():
        np.testing.assert_allclose(getattr(t, name)[0].numpy(), want, rtol=1e-9, err_msg=name)
    # sky + beam on a horizontal surface is GHI
    np.testing.assert_allclose((t.beam * cz + t.sky)[0].numpy(), b["ghi"], rtol=1e-9)
    assert t.ground_lit


def test_direct_beam_reddens_towards_the_horizon():
    """DNI cos θz at 544 nm over 1580 nm: about 6.2 with the sun 10° from the zenith, about 1.2 at 85°, falling
    steadily in between."""
    zeniths = [10.0, 30.0, 45.0, 60.0, 75.0, 85.0]
    t = light_tables("spectrl2", [Sun(zenith_deg=z) for z in zeniths], BANDS)
    ratio = (t.direct_horizontal[:, 0] / t.direct_horizontal[:, 3]).numpy()
    assert abs(ratio[0] - 6.2) < 0.05 and abs(ratio[-1] - 1.2) < 0.05, ratio.round(3).tolist()
    assert np.all(np.diff(ratio) < 0), ratio.round(3).tolist()


# --------------------------------------------------------------------------------- 2. open panels: GHI and ground
def test_monochromatic_band_average_is_the_centre_value():
    """What ``at_centres`` assumes about the package's band averaging: a monochromatic band samples its centre."""
    grid, W = band_sampling(BANDS, dtype=torch.float64)
    assert grid.tolist() == list(CENTRES)
    assert torch.equal(W, torch.eye(4, dtype=torch.float64))


@pytest.mark.parametrize("zenith", [10.0, 45.0, 75.0])
def test_open_horizontal_panel_radiance_is_ghi(zenith):
    """A level Lambertian panel in the open, nothing above or around it: L = ρ (DNI cos θz + DHI) / π (the circumsolar
    part arrives with the beam, the rest with the sky), with a full sky view and no ground in view."""
    rho = 0.4
    meshes = [level("patch", "grey", (0.0, 0.0), (0.6, 0.6)),  # panels beside it, at its height: out of its view
              level("panel_white", "white", (0.0, 0.6), (0.4, 0.4)),
              level("panel_dark", "dark", (0.0, -0.6), (0.4, 0.4))]
    cam = Camera(width=32, height=32, zenith_deg=0.0, range_m=10.0, target=[0.0, 0.0, 0.0], fov_deg=10.0)
    res = render(Scene(MATS, meshes, [cam], [Sun(zenith_deg=zenith)]), sensor=None, dtype=torch.float64)
    px = pixels_of(res, "patch")
    assert int(px.sum()) >= 64
    assert bool(res.lit[0, 0][px].all())
    assert torch.equal(res.gbuffer.sky[0][px], torch.ones(int(px.sum()), dtype=torch.float64))
    assert float(res.gbuffer.ground[0][px].abs().max()) == 0.0
    sp = pvlib_spectra(zenith)
    ghi = at_centres(sp["wavelength"], sp["dni"] * math.cos(math.radians(zenith)) + sp["dhi"])
    expected = torch.tensor(rho * ghi / math.pi)
    torch.testing.assert_close(res.radiance[0, 0][px], expected.expand(int(px.sum()), 4), rtol=1e-3, atol=0)


@pytest.mark.parametrize("zenith", [10.0, 45.0, 75.0])
def test_tilted_panel_on_ground_sees_ground_by_view_factor(zenith):
    """A panel tilted β = 60° facing the sun, standing on a large Lambertian ground of reflectance ρg: sky view
    (1 + cos β)/2, ground view (1 - cos β)/2 (to the ray count's accuracy), the ground-reflected part ρg GHI V_ground,
    and in all pvlib's plane-of-array irradiance (Hay-Davies sky, albedo ρg): L = ρ E_poa / π."""
    rho, rho_g, beta = 0.4, 0.25, 60.0
    cb = math.cos(math.radians(beta))
    mats = {**MATS, "ground": Material(reflectance=rho_g)}
    # lower edge on the ground at x = 0.25, leaning back towards -x; the reference panels lie behind its plane
    # (out of its view) and beside its shadow; the ground is wide enough that no hemisphere ray passes its edge
    meshes = [MeshSpec("patch", "plane", "grey", {"width": 1.0, "height": 1.0}, position=[0.25, 0.0, 0.0],
                       tilt_deg=90.0 - beta),
              level("panel_white", "white", (-0.2, 0.75), (0.3, 0.3), z=0.01),
              level("panel_dark", "dark", (-0.2, -0.75), (0.3, 0.3), z=0.01),
              MeshSpec("ground", "ground", "ground", {"size": 1e5})]
    centre = [0.25 - 0.5 * cb, 0.0, 0.5 * math.sin(math.radians(beta))]
    cam = Camera(width=48, height=48, zenith_deg=beta, azimuth_deg=0.0, range_m=10.0, target=centre, fov_deg=12.0)
    res = render(Scene(mats, meshes, [cam], [Sun(zenith_deg=zenith)]), sensor=None, dtype=torch.float64)
    px = pixels_of(res, "patch")
    n = int(px.sum())
    assert n >= 300
    assert bool(res.lit[0, 0][px].all())
    gb = res.gbuffer
    v_sky = gb.sky[0][px]
    v_ground = gb.ground[0][px][:, gb.material_names.index("ground")]
    assert float(gb.ground[0][px].sum(-1).sub(v_ground).abs().max()) == 0.0  # no other up-facing surface in view
    for v, exact in ((v_sky, (1 + cb) / 2), (v_ground, (1 - cb) / 2)):
        assert float((v - exact).abs().max()) <= PIXEL_TOL
        assert abs(float(v.mean()) - exact) <= mean_tol(n), (float(v.mean()), exact, mean_tol(n))

    b = band_light(zenith)
    cos_i = math.cos(math.radians(beta - zenith))
    # pvlib's plane-of-array irradiance wavelength by wavelength on SPECTRL2's grid, then at the band centres
    sp = pvlib_spectra(zenith)
    ghi_sp = sp["dni"] * math.cos(math.radians(zenith)) + sp["dhi"]
    poa_sp = pv_irradiance.get_total_irradiance(beta, 180.0, zenith, 180.0, sp["dni"], ghi_sp, sp["dhi"],
                                                dni_extra=sp["dni_extra"], albedo=rho_g, model="haydavies")
    poa = {k: at_centres(sp["wavelength"], np.asarray(poa_sp[k])) for k in ("poa_global", "poa_ground_diffuse")}
    L = res.radiance[0, 0][px]
    # per pixel, with the pixel's own view fractions: the shading formula (beam with its circumsolar part, the
    # isotropic sky times V_sky, GHI ρg times V_ground)
    direct = torch.tensor((b["dni"] + b["circumsolar_normal"]) * cos_i)
    sky_part = torch.tensor(b["iso"]) * v_sky[:, None]
    want = rho / math.pi * (direct + sky_part + torch.tensor(b["ghi"] * rho_g) * v_ground[:, None])
    torch.testing.assert_close(L, want, rtol=1e-3, atol=0)
    # the ground-reflected part alone, mean over the panel, against ρg GHI (1 - cos β)/2
    ground_part = (L * math.pi / rho - direct - sky_part).mean(0).numpy()
    np.testing.assert_allclose(ground_part / (rho_g * b["ghi"]), (1 - cb) / 2, atol=mean_tol(n))
    # the whole mean against pvlib's plane-of-array irradiance, within what the view fractions' tolerance allows
    e_poa = np.asarray(poa["poa_global"])
    np.testing.assert_allclose(np.asarray(poa["poa_ground_diffuse"]), b["ghi"] * rho_g * (1 - cb) / 2, rtol=1e-12)
    tol = (b["iso"] + b["ghi"] * rho_g) * mean_tol(n) / e_poa
    rel = L.mean(0).numpy() / (rho * e_poa / math.pi) - 1
    assert np.all(np.abs(rel) <= tol), (rel.tolist(), tol.tolist())


# ------------------------------------------------------------------------------------------------- 3. under a roof
def f_corner(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """View factor from a horizontal element to a parallel x-by-y rectangle at unit height above it, the element
    below one corner (Howell B-3), signed by the quadrant of (x, y)."""
    ax, ay = np.abs(x), np.abs(y)
    sx, sy = np.sqrt(1 + ax**2), np.sqrt(1 + ay**2)
    return np.sign(x) * np.sign(y) * (ax / sx * np.arctan(ay / sx) + ay / sy * np.arctan(ax / sy)) / (2 * np.pi)


def f_rectangle(px, py, x0: float, x1: float, y0: float, y1: float, c: float) -> np.ndarray:
    """View factor from horizontal elements at (px, py) to the rectangle [x0, x1] x [y0, y1] at height c above
    them: four corner rectangles, added and subtracted."""
    X0, X1, Y0, Y1 = (x0 - px) / c, (x1 - px) / c, (y0 - py) / c, (y1 - py) / c
    return f_corner(X1, Y1) - f_corner(X0, Y1) - f_corner(X1, Y0) + f_corner(X0, Y0)


def test_howell_b3_closed_form():
    unit_square = math.atan(1 / math.sqrt(2)) / (math.sqrt(2) * math.pi)  # below the corner of a 1 x 1 square at 1
    assert f_corner(np.array(1.0), np.array(1.0)) == pytest.approx(unit_square)
    assert f_rectangle(0.0, 0.0, -1e6, 1e6, -1e6, 1e6, 1.0) == pytest.approx(1.0, abs=1e-6)  # an infinite roof
    assert f_rectangle(0.0, 0.0, -1e6, 0.0, -1e6, 1e6, 1.0) == pytest.approx(0.5, abs=1e-6)  # half of it
    assert f_rectangle(0.0, 0.0, 2.0, 3.0, -1.0, 1.0, 1.0) == pytest.approx(
        f_rectangle(0.0, 0.0, -3.0, -2.0, -1.0, 1.0, 1.0))  # off to one side, mirrored


@pytest.mark.parametrize("zenith", [10.0, 45.0, 75.0])
def test_panel_under_roof_sees_sky_around_it(zenith):
    """A level panel under an opaque level roof (offset towards the sun by c tan θz, so that it shades the panel
    from the sun and its circumsolar sky): not sunlit, sky view 1 - F_roof (Howell B-3, per pixel, to the ray count's
    accuracy), no ground, and L = ρ E_iso V_sky / π with V_sky the pixel's own sky view."""
    rho, c = 0.4, 0.5
    xr = c * math.tan(math.radians(zenith))
    x0, x1, y0, y1 = -0.5, xr + 0.5, -0.6, 0.6  # the roof: over the panel and its shadow line towards the sun
    mats = {**MATS, "roof": Material(reflectance=0.5)}
    meshes = [level("patch", "grey", (0.0, 0.0), (0.3, 0.3)),
              level("panel_white", "white", (0.0, 0.25), (0.15, 0.15)),
              level("panel_dark", "dark", (0.0, -0.25), (0.15, 0.15)),
              level("roof", "roof", ((x0 + x1) / 2, 0.0), (x1 - x0, y1 - y0), z=c)]
    # the camera hangs under the roof, looking down
    cam = Camera(width=48, height=48, zenith_deg=0.0, range_m=0.3, target=[0.0, 0.0, 0.0], fov_deg=100.0)
    res = render(Scene(mats, meshes, [cam], [Sun(zenith_deg=zenith)]), sensor=None, dtype=torch.float64)
    px = pixels_of(res, "patch")
    n = int(px.sum())
    assert n >= 300
    assert not bool(res.lit[0, 0][px].any())
    gb = res.gbuffer
    assert float(gb.ground[0][px].abs().max()) == 0.0  # the roof's underside is no lit ground
    pos = gb.position[0][px].numpy()
    v_exact = 1 - f_rectangle(pos[:, 0], pos[:, 1], x0, x1, y0, y1, c)
    v = gb.sky[0][px]
    err = v.numpy() - v_exact
    assert np.abs(err).max() <= PIXEL_TOL, np.abs(err).max()
    assert abs(err.mean()) <= mean_tol(n), (err.mean(), mean_tol(n))
    b = band_light(zenith)
    want = rho / math.pi * torch.tensor(b["iso"]) * v[:, None]
    torch.testing.assert_close(res.radiance[0, 0][px], want, rtol=1e-3, atol=0)


# ------------------------------------------------------------------------------- 4. ELM of a patch in the shade
def shade_scene(zenith: float) -> Scene:
    """Two sunlit level reference panels (0.9, 0.05) raised above everything else (an open sky: nothing in their
    hemisphere), and a grey (0.3) level patch on the ground shaded by a wall just towards the sun, tall enough to
    shade it at this sun height; no ground (the patch receives the isotropic sky alone)."""
    wall_h = 1.5 * 0.12 / math.tan(math.radians(zenith))  # the patch's far edge lies 0.12 m from the wall
    mats = {"grey": Material(reflectance=0.3), "white": Material(reflectance=0.9), "dark": Material(reflectance=0.05),
            "wall": Material(reflectance=0.5)}
    meshes = [level("patch", "grey", (0.0, 0.0), (0.1, 0.3)),
              level("panel_white", "white", (0.0, 0.55), (0.3, 0.3), z=wall_h + 0.01),
              level("panel_dark", "dark", (0.0, -0.55), (0.3, 0.3), z=wall_h + 0.01),
              MeshSpec("wall", "plane", "wall", {"width": 0.6, "height": wall_h}, position=[0.07, 0.0, 0.0],
                       yaw_deg=180.0)]
    cam = Camera(width=64, height=64, zenith_deg=0.0, range_m=10.0, target=[0.0, 0.0, 0.0], fov_deg=10.0)
    return Scene(mats, meshes, [cam], [Sun(zenith_deg=zenith)])


def shade_shift_expected(zenith: float) -> tuple[float, float, np.ndarray]:
    """NDGRI and NDSI of E_iso / GHI per band (the ELM reflectance of a grey patch in the shade over its ρ V) and
    that ratio, E_iso by pvlib's Hay-Davies on SPECTRL2's spectra (``band_light``)."""
    b = band_light(zenith)
    r = b["iso"] / b["ghi"]
    return nd(r[0], r[1]), nd(r[2], r[3]), r


@pytest.mark.parametrize("zenith", [10.0, 45.0, 75.0])
def test_elm_of_shaded_grey_patch_reads_the_blue_sky(zenith):
    """ELM against sunlit panels (gain from GHI) reads a grey patch lit by the isotropic sky alone as ρ V E_iso / GHI
    per band: NDGRI and NDSI shift from the grey's 0 by the normalized differences of E_iso / GHI (V cancels)."""
    res = render(shade_scene(zenith), sensor=None, dtype=torch.float64)
    px = pixels_of(res, "patch")
    n = int(px.sum())
    assert n >= 20
    gb = res.gbuffer
    assert not bool(res.lit[0, 0][px].any())
    for p in ("panel_white", "panel_dark"):
        q = pixels_of(res, p)
        assert bool(res.lit[0, 0][q].all()) and float(gb.sky[0][q].min()) == 1.0
    v = gb.sky[0][px]
    assert float(v.mean()) > 0.5  # the patch sees most of the sky
    g_exp, s_exp, ratio = shade_shift_expected(zenith)
    torch.testing.assert_close(res.reflectance[0, 0][px], 0.3 * v[:, None] * torch.tensor(ratio), rtol=1e-6, atol=0)
    g, s = res.ndgri[0, 0][px], res.ndsi[0, 0][px]
    assert float((g - g_exp).abs().max()) <= 0.005, (float(g.mean()), g_exp)
    assert float((s - s_exp).abs().max()) <= 0.005, (float(s.mean()), s_exp)
    # the sky is blue (NDGRI) and its isotropic part, the circumsolar light gone with the beam, bluer still in the
    # SWIR (NDSI): about +0.29/+0.47 at 10°, +0.29/+0.46 at 45°, +0.26/+0.44 at 75°
    assert 0.25 <= float(g.mean()) <= 0.30 and 0.43 <= float(s.mean()) <= 0.48, (float(g.mean()), float(s.mean()))


# ------------------------------------------------------------------------------------------ 5. the thesis lamp
def planck_sun(wavelength_nm: np.ndarray, temperature_k: float = 5950.0) -> np.ndarray:
    """A blackbody's spectral radiance times the solar disc's solid angle, W m^-2 nm^-1 (Planck's law written out)."""
    h, c, k = 6.62607015e-34, 2.99792458e8, 1.380649e-23
    lam = wavelength_nm * 1e-9
    return SUN_SOLID_ANGLE_SR * 2 * h * c**2 / lam**5 / np.expm1(h * c / (lam * k * temperature_k)) * 1e-9


@pytest.mark.parametrize("zenith,azimuth", [(60.0, 30.0), (35.0, -50.0)])
def test_thesis_sun_only_wall(zenith, azimuth):
    """Illumination "thesis", no sky: a vertical Lambertian wall facing +x reads E(λ) cos θi ρ / π, E the blackbody
    sun; nothing else lights it."""
    rho = 0.4
    meshes = [MeshSpec("wall", "plane", "grey", {"width": 1.0, "height": 1.0}, position=[0.0, 0.0, 0.5]),
              MeshSpec("panel_white", "plane", "white", {"width": 1.0, "height": 1.0}, position=[0.0, 1.1, 0.5]),
              MeshSpec("panel_dark", "plane", "dark", {"width": 1.0, "height": 1.0}, position=[0.0, -1.1, 0.5])]
    cam = Camera(width=48, height=24, zenith_deg=90.0, range_m=9.449, target=[0.0, 0.0, 1.0], fov_deg=21.0)
    sun = Sun(zenith_deg=zenith, azimuth_deg=azimuth)
    res = render(Scene(MATS, meshes, [cam], [sun], illumination="thesis"), sensor=None, dtype=torch.float64)
    px = pixels_of(res, "wall")
    assert int(px.sum()) >= 50 and bool(res.lit[0, 0][px].all())
    E = planck_sun(np.array(CENTRES))
    np.testing.assert_allclose(sun_irradiance(sun, torch.tensor(CENTRES, dtype=torch.float64)).numpy(), E, rtol=1e-12)
    cos_i = math.sin(math.radians(zenith)) * math.cos(math.radians(azimuth))
    want = torch.tensor(E * cos_i * rho / math.pi)
    torch.testing.assert_close(res.radiance[0, 0][px], want.expand(int(px.sum()), 4), rtol=1e-9, atol=0)
    assert float(res.light.sky.abs().max()) == 0.0 and float(res.light.ground.abs().max()) == 0.0


def test_thesis_grey_sky_on_open_plane():
    """Illumination "thesis" with ``sky_fraction=0.2``: an open level plane adds 0.2 E ρ / π to its sunlit
    E cos θz ρ / π, at any sun height (the grey sky does not depend on it); no ground light."""
    rho = 0.4
    meshes = [level("patch", "grey", (0.0, 0.0), (0.6, 0.6)),
              level("panel_white", "white", (0.0, 0.6), (0.4, 0.4)),
              level("panel_dark", "dark", (0.0, -0.6), (0.4, 0.4))]
    cam = Camera(width=32, height=32, zenith_deg=0.0, range_m=10.0, target=[0.0, 0.0, 0.0], fov_deg=10.0)
    suns = [Sun(zenith_deg=z, sky_fraction=0.2) for z in (20.0, 70.0)]
    res = render(Scene(MATS, meshes, [cam], suns, illumination="thesis"), sensor=None, dtype=torch.float64)
    px = pixels_of(res, "patch")
    assert bool(res.gbuffer.sky[0][px].eq(1.0).all())
    assert not res.light.ground_lit and float(res.light.ground.abs().max()) == 0.0
    E = torch.tensor(planck_sun(np.array(CENTRES)))
    for k, sun in enumerate(suns):
        sky_term = res.radiance[k, 0][px] - E * math.cos(math.radians(sun.zenith_deg)) * rho / math.pi
        torch.testing.assert_close(sky_term, (0.2 * E * rho / math.pi).expand_as(sky_term), rtol=1e-9, atol=0)


# ------------------------------------------------------------------------------------- a scene without panels
def test_render_without_reference_panels_gives_radiance():
    """No reference panels: the radiance is rendered; there is no ELM, so the reflectance is NaN and nothing is
    detected."""
    meshes = [level("patch", "grey", (0.0, 0.0), (0.6, 0.6))]
    cam = Camera(width=16, height=16, zenith_deg=0.0, range_m=10.0, target=[0.0, 0.0, 0.0], fov_deg=3.0)
    res = render(Scene(MATS, meshes, [cam], [Sun(zenith_deg=45.0)], panels=[]), sensor=None, dtype=torch.float64)
    sp = pvlib_spectra(45.0)
    ghi = at_centres(sp["wavelength"], sp["dni"] * math.cos(math.radians(45.0)) + sp["dhi"])
    torch.testing.assert_close(res.radiance[0, 0, 8, 8], torch.tensor(0.4 * ghi / math.pi), rtol=1e-3, atol=0)
    assert bool(res.reflectance.isnan().all()) and not bool(res.mask.any())
