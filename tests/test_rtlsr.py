"""The "rtlsr" material kind: Ross-Thick / Li-Sparse-Reciprocal kernels (Lucht et al. 2000), their white-sky
integrals, reciprocity, the hotspot, energy bounds and rendering."""

import math

import numpy as np
import pytest
import torch

from torchskin.bands import INDEX_BANDS_NM
from torchskin.render import rtlsr
from torchskin.render.light import sun_irradiance
from torchskin.render.materials import check_material, check_materials, compile_materials
from torchskin.render.pipeline import render
from torchskin.render.scene import Camera, Material, MeshSpec, Scene, Sun

F64 = torch.float64
#: Roy et al. (2016) Table 1, transcribed independently of the module: centre nm, f_iso, f_geo, f_vol
ROY = [(482.0, 0.0774, 0.0079, 0.0372), (561.0, 0.1306, 0.0178, 0.0580), (655.0, 0.1690, 0.0227, 0.0574),
       (865.0, 0.3093, 0.0330, 0.1535), (1609.0, 0.3430, 0.0453, 0.1154), (2201.0, 0.2658, 0.0387, 0.0639)]


def reference_kernels(ti: float, tv: float, phi: float) -> tuple[float, float]:
    """K_vol and K_geo (h/b = 2, b/r = 1) straight from the papers' angle formulas (Lucht et al. 2000)."""
    cos_xi = math.cos(ti) * math.cos(tv) + math.sin(ti) * math.sin(tv) * math.cos(phi)
    xi = math.acos(max(-1.0, min(1.0, cos_xi)))
    k_vol = ((math.pi / 2 - xi) * math.cos(xi) + math.sin(xi)) / (math.cos(ti) + math.cos(tv)) - math.pi / 4
    sec_i, sec_v = 1 / math.cos(ti), 1 / math.cos(tv)
    d2 = math.tan(ti) ** 2 + math.tan(tv) ** 2 - 2 * math.tan(ti) * math.tan(tv) * math.cos(phi)
    cos_t = 2.0 * math.sqrt(d2 + (math.tan(ti) * math.tan(tv) * math.sin(phi)) ** 2) / (sec_i + sec_v)
    t = math.acos(max(-1.0, min(1.0, cos_t)))
    overlap = (t - math.sin(t) * math.cos(t)) * (sec_i + sec_v) / math.pi
    k_geo = overlap - sec_i - sec_v + 0.5 * (1 + cos_xi) * sec_i * sec_v
    return k_vol, k_geo


def roy_weights(rho: float, wl: float) -> tuple[float, float, float]:
    """f_iso, f_vol, f_geo of white-sky albedo ``rho`` with Roy et al.'s ratios interpolated at ``wl`` nm."""
    c = [r[0] for r in ROY]
    r_vol = float(np.interp(wl, c, [r[3] / r[1] for r in ROY]))
    r_geo = float(np.interp(wl, c, [r[2] / r[1] for r in ROY]))
    f_iso = rho / (1 + 0.189184 * r_vol - 1.377622 * r_geo)
    return f_iso, r_vol * f_iso, r_geo * f_iso


def cosines(ti, tv, phi):
    ti, tv, phi = (torch.as_tensor(x, dtype=F64) for x in (ti, tv, phi))
    return torch.cos(ti), torch.cos(tv), torch.cos(ti) * torch.cos(tv) + torch.sin(ti) * torch.sin(tv) * torch.cos(phi)


# ------------------------------------------------------------------------------------------------- kernels
@pytest.mark.parametrize("ti,tv,phi", [(30, 20, 40), (45, 60, 150), (10, 70, 0), (60, 60, 90), (0, 45, 0),
                                       (75, 30, 180), (60, 70, 180), (20, 35, 10), (80, 5, 120)])
def test_kernels_match_the_angle_formulas(ti, tv, phi):
    ci, cv, cx = cosines(*(math.radians(a) for a in (ti, tv, phi)))
    k_vol, k_geo = reference_kernels(*(math.radians(a) for a in (ti, tv, phi)))
    assert abs(float(rtlsr.ross_thick(ci, cv, cx)) - k_vol) < 1e-9
    assert abs(float(rtlsr.li_sparse_r(ci, cv, cx)) - k_geo) < 1e-9


def test_kernels_vanish_at_nadir():
    one = torch.ones((), dtype=F64)
    assert abs(float(rtlsr.ross_thick(one, one, one))) < 1e-12
    assert abs(float(rtlsr.li_sparse_r(one, one, one))) < 1e-12


def principal_plane_k_geo(theta_i: float) -> tuple[torch.Tensor, torch.Tensor, int]:
    tv = torch.arange(-89.0, 89.01, 0.25, dtype=F64)  # signed view zenith: > 0 on the sun's side (φ = 0)
    ti = torch.full_like(tv, theta_i)
    cos_xi = torch.cos(torch.deg2rad(ti - tv))
    k = rtlsr.li_sparse_r(torch.cos(torch.deg2rad(ti)), torch.cos(torch.deg2rad(tv)), cos_xi)
    return tv, k, int(torch.nonzero(tv == theta_i))


@pytest.mark.parametrize("theta_i", [10.0, 20.0, 30.0, 35.0])
def test_hotspot_is_the_principal_plane_maximum_of_k_geo(theta_i):
    tv, k, hot = principal_plane_k_geo(theta_i)
    assert int(k.argmax()) == hot  # over every view zenith up to 89°
    sec = 1 / math.cos(math.radians(theta_i))
    assert abs(float(k[hot]) - (sec * sec - sec)) < 1e-6  # hotspot: O = sec θ, so K_geo = sec²θ - sec θ


@pytest.mark.parametrize("theta_i", [40.0, 45.0, 50.0, 55.0, 60.0, 70.0, 80.0])
def test_k_geo_has_a_cusp_at_the_hotspot(theta_i):
    # the shadows' overlap is whole at the hotspot: K_geo's slope along the principal plane drops there (up to
    # θi = 55° a local maximum; beyond it, LiSparse-R's reciprocal sec θi sec θv term keeps K_geo rising towards
    # the grazing backscatter view, so the hotspot is no longer the maximum)
    tv, k, hot = principal_plane_k_geo(theta_i)
    left, right = float(k[hot] - k[hot - 1]), float(k[hot + 1] - k[hot])
    assert left - right > 0.01 * abs(left) + 1e-4
    if theta_i <= 55.0:
        assert left > 0 > right
    sec = 1 / math.cos(math.radians(theta_i))
    assert abs(float(k[hot]) - (sec * sec - sec)) < 1e-6 * sec * sec


def test_brdf_is_reciprocal():
    g = torch.Generator().manual_seed(7)
    w = torch.randn(2, 4000, 3, generator=g, dtype=F64)
    w = w / w.norm(dim=-1, keepdim=True)
    w[..., 2] = w[..., 2].abs()  # upper hemisphere
    ci, cv, cx = w[0, :, 2:], w[1, :, 2:], (w[0] * w[1]).sum(-1, keepdim=True)
    f = rtlsr.kernel_weights(torch.tensor(0.2, dtype=F64), torch.tensor(list(INDEX_BANDS_NM), dtype=F64))
    a, b = rtlsr.rtlsr_brdf_cos(ci, cv, cx, *f), rtlsr.rtlsr_brdf_cos(cv, ci, cx, *f)
    assert a.shape == (4000, 4) and bool((a > 0).any())
    assert float(((a - b).abs() / a.abs().clamp_min(1e-300)).max()) <= 4 * torch.finfo(F64).eps


def test_white_sky_integrals_of_the_kernels():
    # h_k = (1/π²) ∫∫ K cos θi cos θv dω_i dω_v = (4/π) ∫_0^1 ∫_0^1 ∫_0^π K μi μv dφ dμi dμv (K even in φ)
    x, w = np.polynomial.legendre.leggauss(96)
    mu, wmu = torch.tensor((x + 1) / 2, dtype=F64), torch.tensor(w / 2, dtype=F64)
    phi, wphi = torch.tensor((x + 1) * math.pi / 2, dtype=F64), torch.tensor(w * math.pi / 2, dtype=F64)
    mi, mv, p = mu[:, None, None], mu[None, :, None], phi[None, None, :]
    cx = mi * mv + torch.sqrt((1 - mi * mi) * (1 - mv * mv)) * torch.cos(p)
    weight = (wmu * mu)[:, None, None] * (wmu * mu)[None, :, None] * wphi * (4 / math.pi)
    assert abs(float(weight.sum()) - 1) < 1e-12  # the measure: an isotropic R = 1 has white-sky albedo 1
    h_vol = float((rtlsr.ross_thick(mi, mv, cx) * weight).sum())
    h_geo = float((rtlsr.li_sparse_r(mi, mv, cx) * weight).sum())
    assert abs(h_vol - 0.189184) < 2e-3 and abs(h_geo - (-1.377622)) < 2e-3
    assert (rtlsr.WSA_VOL, rtlsr.WSA_GEO) == (0.189184, -1.377622)


def test_brdf_is_finite_and_zero_below_the_horizon():
    c = torch.tensor([-1.0, -0.3, 0.0, 1e-9, 1e-4, 0.01, 0.5, 1.0], dtype=F64)
    ci, cv, cx = c[:, None, None, None], c[None, :, None, None], c[None, None, :, None]
    f = rtlsr.kernel_weights(torch.tensor(rtlsr.RHO_MAX, dtype=F64), torch.tensor([544.0, 1580.0], dtype=F64))
    for dt in (F64, torch.float32):
        out = rtlsr.rtlsr_brdf_cos(ci.to(dt), cv.to(dt), cx.to(dt), *(x.to(dt) for x in f))
        assert out.dtype == dt and out.shape == (8, 8, 8, 2)
        assert bool(torch.isfinite(out).all()) and bool((out >= 0).all())
        assert bool((out[:3] == 0).all()) and bool((out[:, :3] == 0).all())


# ---------------------------------------------------------------------------------------- kernel weights
def test_kernel_weights_follow_roy_2016_and_the_white_sky_albedo():
    wl = torch.tensor([300.0, 482.0, 544.0, 865.0, 1234.5, 2201.0, 2500.0], dtype=F64)
    f_iso, f_vol, f_geo = rtlsr.kernel_weights(torch.tensor(0.2, dtype=F64), wl)
    for k, x in enumerate(wl.tolist()):
        ref = roy_weights(0.2, x)  # np.interp holds the end values outside 482-2201 nm, as documented
        assert abs(float(f_iso[k]) - ref[0]) < 1e-12
        assert abs(float(f_vol[k]) - ref[1]) < 1e-12
        assert abs(float(f_geo[k]) - ref[2]) < 1e-12
    assert torch.allclose(f_iso + 0.189184 * f_vol - 1.377622 * f_geo, torch.full_like(wl, 0.2), atol=1e-15)
    assert abs(float(f_vol[3] / f_iso[3]) - 0.1535 / 0.3093) < 1e-12  # NIR: f_vol / f_iso of Table 1


def test_black_sky_albedo_quadrature():
    ci = torch.cos(torch.deg2rad(torch.tensor([0.0, 30.0, 60.0, 85.0], dtype=F64)))
    iso = rtlsr.black_sky_albedo(ci, torch.tensor([0.3], dtype=F64), torch.zeros(1, dtype=F64),
                                 torch.zeros(1, dtype=F64), n=20)
    assert torch.allclose(iso, torch.full_like(iso, 0.3), atol=1e-13)  # Lambertian: DHR = R
    # white-sky albedo = ∫ DHR(θi) 2 cos θi dcos θi: of R = 1 + K_vol (never negative), 1 + 0.189184
    x, w = np.polynomial.legendre.leggauss(48)
    mu, wmu = torch.tensor((x + 1) / 2, dtype=F64), torch.tensor(w / 2, dtype=F64)
    one = torch.ones(1, dtype=F64)
    dhr = rtlsr.black_sky_albedo(mu, one, one, 0 * one, n=48)[:, 0]
    assert abs(float((dhr * 2 * mu * wmu).sum()) - (1 + 0.189184)) < 2e-3


@pytest.mark.parametrize("bands", [list(INDEX_BANDS_NM), [400.0, 561.0, 1700.0]])  # the model admits 400-1700 nm
def test_black_sky_albedo_stays_below_one_in_the_documented_range(bands):
    mats = {"m": Material("rtlsr", reflectance=rtlsr.RHO_MAX)}
    t = compile_materials(mats, [[b, 0.0] for b in bands], [Sun()], dtype=F64)
    p = t.groups["rtlsr"].params
    ci = torch.cos(torch.deg2rad(torch.arange(0.0, rtlsr.DHR_ZENITH_MAX_DEG + 0.5, 1.0, dtype=F64)))
    dhr = rtlsr.black_sky_albedo(ci, p["f_iso"], p["f_vol"], p["f_geo"], n=40)  # (zeniths, B)
    assert dhr.shape == (len(ci), len(bands))
    assert bool((dhr > 0).all()) and float(dhr.max()) <= 1.0
    assert torch.equal(t.albedo[0], torch.full((len(bands),), rtlsr.RHO_MAX, dtype=F64))  # albedo: white-sky


def test_the_range_is_tight_and_the_kind_refuses_above_it():
    above = rtlsr.RHO_MAX + 1e-3
    f = rtlsr.kernel_weights(torch.tensor(above, dtype=F64), torch.tensor([865.0], dtype=F64))  # the worst: NIR
    assert float(rtlsr.black_sky_albedo(math.cos(math.radians(rtlsr.DHR_ZENITH_MAX_DEG)), *f, n=40)[0]) > 1.0
    check_material(Material("rtlsr", reflectance=rtlsr.RHO_MAX))
    with pytest.raises(ValueError, match="reflectance"):
        check_material(Material("rtlsr", reflectance=above))
    with pytest.raises(ValueError, match="reflectance"):
        check_material(Material("rtlsr", reflectance=[0.1, 0.2, above, 0.1]))


@pytest.mark.parametrize("kwargs,match", [
    ({}, "reflectance"),
    ({"reflectance": -0.1}, "reflectance"),
    ({"reflectance": 0.1, "params": {"kernels": "modis"}}, "'kernels'"),
    ({"reflectance": 0.1, "params": {"kernels": 3}}, "'kernels'"),
    ({"reflectance": 0.1, "params": {"kernel": "roy2016"}}, "kernel"),
])
def test_the_kind_refuses_bad_materials(kwargs, match):
    with pytest.raises(ValueError, match=match):
        check_material(Material("rtlsr", **kwargs))
    with pytest.raises(ValueError, match="material 'soil'"):
        check_materials({"soil": Material("rtlsr", **kwargs)})


# ------------------------------------------------------------------------------------------------- render
def soil_scene(cam_az: float, rho: float = 0.2) -> Scene:
    mats = {"soil": Material("rtlsr", reflectance=rho), "white": Material(reflectance=0.9),
            "dark": Material(reflectance=0.05)}
    meshes = [MeshSpec("ground", "plane", "soil", {"width": 40, "height": 40}, position=[20, 0, 0], tilt_deg=90.0),
              MeshSpec("panel_white", "plane", "white", {"width": 0.5, "height": 0.5}, position=[0.25, 0.7, 0.01],
                       tilt_deg=90.0),
              MeshSpec("panel_dark", "plane", "dark", {"width": 0.5, "height": 0.5}, position=[0.25, -0.7, 0.01],
                       tilt_deg=90.0)]
    cam = Camera(width=16, height=16, zenith_deg=40.0, azimuth_deg=cam_az, target=[0, 0, 0], fov_deg=14.0)
    return Scene(mats, meshes, [cam], [Sun(zenith_deg=40.0, azimuth_deg=0.0)], illumination="thesis")


def test_rendered_plane_radiance_is_e_cos_r_over_pi():
    sc = soil_scene(cam_az=60.0)
    res = render(sc, sensor=None, dtype=F64)
    gb = res.gbuffer
    ground = gb.mesh[0] == gb.mesh_names.index("ground")
    L = res.radiance[0, 0][ground]  # (P, B)
    assert int(ground.sum()) > 100 and bool(torch.isfinite(res.radiance).all()) and bool((res.radiance >= 0).all())
    view = gb.view[0][ground]
    sun = sc.suns[0]
    ti = math.radians(sun.zenith_deg)
    for k, b in enumerate(INDEX_BANDS_NM):
        E = float(sun_irradiance(sun, torch.tensor(b, dtype=F64)))
        f_iso, f_vol, f_geo = roy_weights(0.2, b)
        for px in range(0, len(view), 17):
            v = view[px].tolist()
            tv = math.acos(v[2])
            phi = math.atan2(v[1], v[0]) - math.radians(sun.azimuth_deg)
            k_vol, k_geo = reference_kernels(ti, tv, phi)
            want = E * math.cos(ti) * max(0.0, f_iso + f_vol * k_vol + f_geo * k_geo) / math.pi
            assert abs(float(L[px, k]) - want) <= 1e-6 * want  # the G-buffer's geometry is float32


def test_backscatter_is_brighter_than_forward_scatter():
    back = render(soil_scene(cam_az=0.0), sensor=None)  # the sun behind the camera: the hotspot
    fwd = render(soil_scene(cam_az=180.0), sensor=None)

    def mean_ground(res):
        g = res.gbuffer.mesh[0] == res.gbuffer.mesh_names.index("ground")
        assert int(g.sum()) > 100
        return res.radiance[0, 0][g].mean(0)

    for res in (back, fwd):
        assert bool(torch.isfinite(res.radiance).all()) and bool((res.radiance >= 0).all())
    assert bool((mean_ground(back) > 1.3 * mean_ground(fwd)).all())
