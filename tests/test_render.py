"""Renderer: radiometry, ELM, shadows, local angles, glints, backends and input errors."""

import math

import numpy as np
import pytest
import torch

from torchskin import tissue
from torchskin.render.light import sun_irradiance
from torchskin.render.meshes import build_mesh
from torchskin.render.pipeline import render, render_pixels
from torchskin.render.raycast import SKY_RAYS
from torchskin.render.scene import Camera, Material, MeshSpec, Scene, Sun, direction
from torchskin.render.sensor import Sensor

DEG = math.pi / 180


def panel_scene(sun_az=0.0, sun_zen=90.0, cam_az=0.0, target_refl=(0.2, 0.37, 0.55, 0.8), extra=(), width=96,
                height=48, sky=0.0):
    mats = {"white": Material("lambertian", reflectance=0.97), "dark": Material("lambertian", reflectance=0.03),
            "target": Material("lambertian", reflectance=list(target_refl)), "skin": Material("skin")}
    meshes = [
        MeshSpec("panel_white", "plane", "white", params={"width": 1.0, "height": 1.0}, position=[0.0, 1.1, 0.5]),
        MeshSpec("target", "plane", "target", params={"width": 1.0, "height": 1.0}, position=[0.0, 0.0, 0.5]),
        MeshSpec("panel_dark", "plane", "dark", params={"width": 1.0, "height": 1.0}, position=[0.0, -1.1, 0.5]),
        *extra,
    ]
    cam = Camera(width=width, height=height, zenith_deg=90.0, azimuth_deg=cam_az, range_m=9.449,
                 target=[0.0, 0.0, 1.0], fov_deg=21.0)
    return Scene(mats, meshes, [cam], [Sun(zenith_deg=sun_zen, azimuth_deg=sun_az, sky_fraction=sky)],
                 illumination="thesis")  # the thesis's lamp: these tests check its closed forms


def mesh_pixels(res, name, c=0):
    return res.gbuffer.mesh[c] == res.gbuffer.mesh_names.index(name)


@pytest.mark.parametrize("sun_az,cam_az", [(0.0, 0.0), (40.0, 0.0), (80.0, 0.0), (-60.0, 30.0)])
def test_elm_recovers_lambertian_reflectance(sun_az, cam_az):
    sc = panel_scene(sun_az=sun_az, cam_az=cam_az)
    truth = torch.tensor([0.2, 0.37, 0.55, 0.8])
    ideal = render(sc, sensor=Sensor(noise=False, quantize=False))
    px = mesh_pixels(ideal, "target")
    assert int(px.sum()) > 100
    assert float((ideal.reflectance[0, 0][px] - truth).abs().max()) < 1e-4
    noisy = render(sc, sensor=Sensor(noise=True, seed=3))
    est = noisy.reflectance[0, 0][px]
    assert float((est.median(dim=0).values - truth).abs().max()) < 0.02
    assert float(est.std(dim=0).max()) < 0.02


def test_appendix_c_middle_panel():
    from torchskin.experiment import appendix_c

    assert abs(appendix_c(Sensor()) - 0.40) <= 0.02
    assert abs(appendix_c(None) - 0.40) < 1e-5


def test_lambertian_sphere_radiance_follows_cosine():
    mats = {"white": Material("lambertian", reflectance=0.97), "dark": Material("lambertian", reflectance=0.03),
            "grey": Material("lambertian", reflectance=0.5)}
    centre = np.array([0.0, 0.0, 1.0])
    meshes = [MeshSpec("ball", "sphere", "grey", params={"radius": 0.4, "subdivisions": 5}, position=list(centre)),
              MeshSpec("panel_white", "plane", "white", params={"width": 0.3, "height": 0.3}, position=[0, 0.7, 0.4]),
              MeshSpec("panel_dark", "plane", "dark", params={"width": 0.3, "height": 0.3}, position=[0, -0.7, 0.4])]
    sun = Sun(zenith_deg=60.0, azimuth_deg=35.0)
    sc = Scene(mats, meshes, [Camera(width=160, height=160, range_m=9.449, target=[0, 0, 1.0], fov_deg=12.0)], [sun],
               illumination="thesis")
    res = render(sc, sensor=None, dtype=torch.float64)
    gb = res.gbuffer
    px = mesh_pixels(res, "ball")
    n_true = gb.position[0][px] - torch.tensor(centre)
    n_true = n_true / n_true.norm(dim=-1, keepdim=True)  # the sphere's own normal at the hit point
    cos_true = n_true @ torch.tensor(sun.direction)
    E = float(sun_irradiance(sun, torch.tensor([633.0], dtype=torch.float64)))
    L = res.radiance[0, 0][px][:, 1]
    sel = cos_true > 0.05  # away from the terminator
    rel = (L[sel] / (0.5 / math.pi * E) - cos_true[sel]) / cos_true[sel]
    assert int(sel.sum()) > 2000
    assert float(rel.abs().max()) < 1e-3


def test_occluded_surface_keeps_only_the_sky_term():
    plate = MeshSpec("plate", "ground", "dark", params={"size": 0.3}, position=[0.0, 0.0, 3.0])
    ground = MeshSpec("floor", "ground", "target", params={"size": 2.0})
    mats_extra = [plate, ground]
    sc = panel_scene(sun_zen=0.0, extra=mats_extra, sky=0.2)
    sc.cameras = [Camera(width=128, height=128, zenith_deg=45.0, azimuth_deg=0.0, range_m=8.0, target=[0, 0, 0.5],
                         fov_deg=30.0)]
    res = render(sc, sensor=None, dtype=torch.float64)
    floor = mesh_pixels(res, "floor")
    shadow = res.gbuffer.shadow[0, 0] & floor
    lit = ~res.gbuffer.shadow[0, 0] & floor
    assert int(shadow.sum()) > 20 and int(lit.sum()) > 100
    rho = torch.tensor([0.2, 0.37, 0.55, 0.8], dtype=torch.float64)
    E = torch.stack([sun_irradiance(sc.suns[0], torch.tensor(b, dtype=torch.float64)) for b in (544., 633., 1080., 1580.)])
    # horizontal floor: the sky it sees, V (its cosine-weighted sky view from hemisphere rays: the plate above, the
    # target and panels standing near it take part of it; view factors themselves: tests/test_render_light.py)
    V = res.gbuffer.sky[0][shadow]
    assert 0.5 < float(V.min()) and float(V.max()) <= 1.0
    sky_only = rho / math.pi * 0.2 * E * V[:, None]
    torch.testing.assert_close(res.radiance[0, 0][shadow], sky_only, rtol=1e-6, atol=0)
    Vl = res.gbuffer.sky[0][lit]
    torch.testing.assert_close(res.radiance[0, 0][lit], rho / math.pi * E * (1 + 0.2 * Vl[:, None]), rtol=1e-6, atol=0)
    # the shadow sits under the plate, straight below (sun at zenith)
    pos = res.gbuffer.position[0][shadow]
    assert float(pos[:, :2].abs().max()) <= 0.3 + 1e-3


def test_cylinder_local_angles_match_appendix_a():
    """Appendix A: a cylinder of radius r whose front is R from the camera; a point (x, y) on it has
    θ_rot = atan(y/x), θ_i,local = θ_i,global - θ_rot and θ_r,local = θ_rot + atan(y / (R + r - x)) (the
    thesis prints the last arctangent inverted, which gives -90 degrees at the front)."""
    r, R, theta_g = 0.1, 3.0, 25.0
    mats = {"white": Material("lambertian", reflectance=0.97), "dark": Material("lambertian", reflectance=0.03),
            "skin": Material("skin")}
    meshes = [MeshSpec("cyl", "cylinder", "skin", params={"radius": r, "height": 1.0, "segments": 512}),
              MeshSpec("panel_white", "plane", "white", params={"width": 0.2, "height": 0.2}, position=[0, 0.25, 0.4]),
              MeshSpec("panel_dark", "plane", "dark", params={"width": 0.2, "height": 0.2}, position=[0, -0.25, 0.4])]
    cam = Camera(width=400, height=41, zenith_deg=90.0, azimuth_deg=0.0, range_m=R + r, target=[0, 0, 0.5],
                 fov_deg=12.0)
    sc = Scene(mats, meshes, [cam], [Sun(zenith_deg=90.0, azimuth_deg=theta_g)], illumination="thesis")
    gb = render(sc, sensor=None, dtype=torch.float64).gbuffer
    row = 20  # the central row: horizontal rays through the cylinder's mid-height
    hit = (gb.mesh[0, row] == 0)
    p = gb.position[0, row][hit]
    alpha = torch.atan2(p[:, 1], p[:, 0])
    keep = alpha.abs() < 60 * DEG  # away from the silhouette
    n = gb.normal[0, row][hit]
    s = torch.tensor(direction(90.0, theta_g))
    ti = torch.acos((n @ s).clamp(-1, 1))
    tr = torch.acos((n * gb.view[0, row][hit]).sum(-1).clamp(-1, 1))
    ti_closed = (theta_g * DEG - alpha).abs()
    tr_closed = (alpha + torch.atan(p[:, 1] / (R + r - p[:, 0]))).abs()
    assert int(keep.sum()) > 50
    assert float((ti - ti_closed)[keep].abs().max()) < 0.5 * DEG
    assert float((tr - tr_closed)[keep].abs().max()) < 0.5 * DEG


def test_skin_glint_peaks_where_half_vector_meets_normal():
    mats = {"white": Material("lambertian", reflectance=0.97), "dark": Material("lambertian", reflectance=0.03),
            "skin": Material("skin")}
    meshes = [MeshSpec("ball", "sphere", "skin", params={"radius": 0.3, "subdivisions": 5}, position=[0, 0, 1.0]),
              MeshSpec("panel_white", "plane", "white", params={"width": 0.2, "height": 0.2}, position=[0, 0.5, 0.3]),
              MeshSpec("panel_dark", "plane", "dark", params={"width": 0.2, "height": 0.2}, position=[0, -0.5, 0.3])]
    cam = Camera(width=200, height=200, zenith_deg=80.0, azimuth_deg=0.0, range_m=9.449, target=[0, 0, 1.0],
                 fov_deg=8.0)
    sun = Sun(zenith_deg=60.0, azimuth_deg=30.0)
    res = render(Scene(mats, meshes, [cam], [sun], illumination="thesis"), sensor=Sensor(noise=False))
    gb = res.gbuffer
    px = (gb.mesh[0] == 0) & res.lit[0, 0]
    refl = torch.where(px, res.reflectance[0, 0, :, :, 3], torch.zeros(()))
    k = int(torch.argmax(refl))
    n = gb.normal[0].reshape(-1, 3)[k]
    v = gb.view[0].reshape(-1, 3)[k]
    s = torch.tensor(sun.direction, dtype=torch.float32)
    h = (s + v) / (s + v).norm()
    assert math.degrees(math.acos(float((n @ h).clamp(-1, 1)))) < 2.0
    # the glint is far brighter than the diffuse skin and drives the indices towards 0
    assert float(refl.max()) > 3 * float(res.reflectance[0, 0, :, :, 3][px].median())


def test_float32_and_float64_renders_agree():
    sc = panel_scene(sun_az=30.0, extra=[MeshSpec("ball", "sphere", "skin", params={"radius": 0.3},
                                                 position=[1.0, 0.0, 1.4])])
    sens = Sensor(noise=False, quantize=False)
    a = render(sc, sensor=sens, dtype=torch.float32)
    b = render(sc, sensor=sens, dtype=torch.float64)
    hit = a.gbuffer.hit[0]
    ra, rb = a.reflectance[0, 0][hit].double(), b.reflectance[0, 0][hit]
    lit = rb.abs() > 1e-3
    assert float(((ra - rb).abs() / rb.abs())[lit].max()) < 1e-4


def test_render_runs_on_every_device(device):
    dt = torch.float32
    sc = panel_scene(sun_az=20.0, extra=[MeshSpec("ball", "sphere", "skin", params={"radius": 0.3},
                                                 position=[1.0, 0.0, 1.4])])
    res = render(sc, device=device, dtype=dt, sensor=Sensor(noise=False))
    assert res.reflectance.device.type == device.type
    ref = render(sc, device="cpu", dtype=dt, sensor=Sensor(noise=False))
    torch.testing.assert_close(res.reflectance.cpu(), ref.reflectance, rtol=1e-4, atol=1e-4)


def test_several_suns_and_cameras_in_one_call_match_single_renders():
    sc = panel_scene(extra=[MeshSpec("ball", "sphere", "skin", params={"radius": 0.3}, position=[1.0, 0.0, 1.4])])
    sc.suns = [Sun(zenith_deg=90.0, azimuth_deg=a) for a in (0.0, 30.0, -50.0)]
    sc.cameras = [Camera(width=96, height=48, azimuth_deg=a, target=[0.0, 0.0, 1.0], fov_deg=21.0) for a in (0.0, 20.0)]
    both = render(sc, sensor=None)
    for si, sun in enumerate(sc.suns):
        for ci, cam in enumerate(sc.cameras):
            one = Scene(sc.materials, sc.meshes, [cam], [sun], illumination=sc.illumination)
            torch.testing.assert_close(render(one, sensor=None).radiance[0, 0], both.radiance[si, ci])


def test_scene_json_round_trip(tmp_path):
    sc = panel_scene(sun_az=30.0)
    path = tmp_path / "scene.json"
    sc.to_json(path)
    back = Scene.from_json(path)
    assert back.to_dict() == sc.to_dict()
    torch.testing.assert_close(render(back, sensor=None).radiance, render(sc, sensor=None).radiance)


def test_diffuse_only_skin_is_lambertian_with_the_diffuse_model_reflectance():
    sc = panel_scene(sun_az=35.0, extra=[MeshSpec("slab", "plane", "skin", params={"width": 0.5, "height": 0.5},
                                                  position=[0.5, 0.0, 1.6])])
    sc.materials["skin"] = Material("skin", skin="V-VI", specular=False)
    res = render(sc, sensor=None, dtype=torch.float64)
    px = mesh_pixels(res, "slab")
    expect = tissue.reflectance(tissue.preset("V-VI", dtype=torch.float64),
                                torch.tensor([544.0, 633.0, 1080.0, 1580.0], dtype=torch.float64))
    torch.testing.assert_close(res.reflectance[0, 0][px], expect.expand(int(px.sum()), 4), rtol=1e-9, atol=1e-9)


def test_bad_inputs_raise_clear_errors(tmp_path):
    with pytest.raises(ValueError, match="zenith must lie in"):
        Sun(zenith_deg=120.0 + 90)
    with pytest.raises(ValueError, match="at least 1 x 1"):
        Camera(width=0)
    with pytest.raises(ValueError, match="does not exist"):
        build_mesh(MeshSpec("m", "file", "skin", params={"path": str(tmp_path / "missing.obj")}))
    empty = tmp_path / "empty.obj"
    empty.write_text("# nothing\n")
    with pytest.raises(ValueError, match="no triangles"):
        build_mesh(MeshSpec("m", "file", "skin", params={"path": str(empty)}))
    broken = tmp_path / "broken.obj"
    broken.write_text("v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n")  # one degenerate triangle
    with pytest.raises(ValueError, match="degenerate"):
        build_mesh(MeshSpec("m", "file", "skin", params={"path": str(broken)}))
    sc = panel_scene()
    sc.cameras = [Camera(width=32, height=32, zenith_deg=0.0, target=[0.0, 0.0, 20.0], range_m=5.0)]  # sky only
    with pytest.raises(ValueError, match="ELM impossible"):
        render(sc)
    with pytest.raises(ValueError, match="unknown material"):
        Scene({}, [MeshSpec("m", "plane", "nope")], [Camera()], [Sun()], panels=[])


def test_mesh_file_subject_renders(tmp_path):
    from torchskin.render.meshes import sphere_mesh, write_obj

    v, f = sphere_mesh(0.3, 3)
    path = tmp_path / "ball.obj"
    write_obj(path, v, f)
    sc = panel_scene(sun_az=10.0, extra=[MeshSpec("scan", "file", "skin", params={"path": str(path)},
                                                  position=[1.0, 0.0, 1.4])])
    res = render(sc, sensor=Sensor(noise=False))
    assert int(res.skin[0].sum()) > 50


def test_cli_render_rejects_bad_angles(capsys, tmp_path):
    from torchskin.cli import main

    assert main(["render", "--out", str(tmp_path), "--source-zenith", "95"]) == 2
    assert "--source-zenith must lie in [0, 90]" in capsys.readouterr().err
    assert main(["render", "--out", str(tmp_path), "--width", "0"]) == 2
    assert "resolution" in capsys.readouterr().err


def test_skin_slab_reads_the_combined_brdf_through_elm():
    """Skin and panels share a normal, so ELM returns π f(θi, θr, Δφ) cos θi / cos θi = π f exactly (eq 3.1.1
    with ρ_d from the exact closed form at R0 = Schlick(ρ0, θi))."""
    from torchskin.optics import THESIS_SPECULAR, combined_brdf

    slab = MeshSpec("slab", "plane", "skin", params={"width": 0.4, "height": 0.4}, position=[0.0, 0.0, 1.7])
    sc = panel_scene(sun_az=30.0, sun_zen=80.0, extra=[slab])
    sc.meshes[1] = MeshSpec("target", "plane", "target", params={"width": 1.0, "height": 0.3}, position=[0, 0, 0.2])
    res = render(sc, sensor=None, dtype=torch.float64)
    gb = res.gbuffer
    px = mesh_pixels(res, "slab")
    n = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    s = torch.tensor(direction(80.0, 30.0))
    v = gb.view[0][px].double()
    ti = torch.acos(s @ n).expand(v.shape[0])
    tr = torch.acos(v @ n)
    s_t = s - (s @ n) * n
    v_t = v - (v @ n)[:, None] * n
    dphi = torch.acos(((v_t @ s_t) / (v_t.norm(dim=-1) * s_t.norm())).clamp(-1, 1))
    wl = torch.tensor([544.0, 633.0, 1080.0, 1580.0], dtype=torch.float64)
    sig, rho0 = THESIS_SPECULAR.at(wl)
    rho_d = tissue.diffuse_reflectance(tissue.preset("I-II", dtype=torch.float64), wl, theta_i=ti[:1], rho0=rho0)
    f = combined_brdf(ti[:, None], tr[:, None], dphi[:, None], rho_d, sig, rho0)
    torch.testing.assert_close(res.reflectance[0, 0][px], math.pi * f, rtol=2e-5, atol=1e-6)


@pytest.mark.parametrize("surface", ["thesis", "conserving"])
def test_flat_skin_panel_matches_each_surface_model_closed_form(surface):
    """A flat skin panel beside the ELM panels (same normal), sensor chain on with noise and quantisation off,
    far from the specular lobe (facet tilt 45°): ELM reads (1 - ρ_Schlick(β)) ρ_d with
    ρ_d = R0 + (1-R0)² R_sub / (1 - R0 R_sub) ("thesis") or (1-R0)² R_sub / (1 - R0 R_sub) ("conserving"),
    R0 = Schlick(ρ0, θi), to 1e-4."""
    from torchskin.optics import THESIS_SPECULAR

    sc = panel_scene(sun_az=80.0, cam_az=10.0)
    sc.materials["target"] = Material("skin", skin="I-II", surface=surface)
    res = render(sc, sensor=Sensor(noise=False, quantize=False))
    px = mesh_pixels(res, "target")
    assert int(px.sum()) > 100
    wl = torch.tensor([544.0, 633.0, 1080.0, 1580.0], dtype=torch.float64)
    _, rho0 = THESIS_SPECULAR.at(wl)
    r_sub = tissue.subsurface_reflectance(tissue.preset("I-II", dtype=torch.float64), wl)
    n, s = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64), torch.tensor(direction(90.0, 80.0))
    v = res.gbuffer.view[0][px].double()
    cos_b = torch.sqrt(0.5 * (1 + v @ s))[:, None]  # cos β from cos 2β = ω_i · ω_r
    r0 = rho0 + (1 - rho0) * (1 - s @ n) ** 5
    sub = (1 - r0) ** 2 * r_sub / (1 - r0 * r_sub)
    rho_d = r0 + sub if surface == "thesis" else sub
    want = (1 - (rho0 + (1 - rho0) * (1 - cos_b) ** 5)) * rho_d
    got = res.reflectance[0, 0][px].double()
    assert float((got - want).abs().max()) < 1e-4
    # the two models differ by (1 - F(β)) R0 here: about 0.4 of reflectance at 80° incidence
    if surface == "thesis":
        assert float((want - (1 - (rho0 + (1 - rho0) * (1 - cos_b) ** 5)) * sub).min()) > 0.03


@pytest.mark.slow
def test_spectralon_brdf_panel_behaviour():
    """Lambertian at normal incidence; the BRDF seen at θr = 0 drops by the thesis's 4.1 % (VIS) and 7.4 %
    (NIR) at 75° incidence; the lobe takes the diffuse energy, so the DHR stays within 1.5 % of ρ."""
    from torchskin.optics import dhr, spectralon_brdf_cos

    wl = torch.tensor([544.0, 633.0, 1080.0, 1580.0], dtype=torch.float64)
    rho = torch.tensor([0.989, 0.990, 0.992, 0.988], dtype=torch.float64)

    def f(ti, tr, dp):
        ci, cr = torch.cos(ti), torch.cos(tr)
        c2b = ci * cr + torch.sin(ti) * torch.sin(tr) * torch.cos(dp)
        return spectralon_brdf_cos(ci, cr, c2b, rho, wl)

    z = torch.zeros(1, 1, dtype=torch.float64)
    f0 = f(z, z, z)[0]
    torch.testing.assert_close(f0, rho / math.pi)
    f75 = f(torch.full((1, 1), 75 * DEG, dtype=torch.float64), z, z)[0]
    torch.testing.assert_close(f75 / f0 - 1, torch.tensor([-0.041, -0.041, -0.074, -0.074], dtype=torch.float64))
    for a in (0.0, 40.0, 75.0):
        d = dhr(lambda ti, tr, dp: f(ti[..., None], tr[..., None], dp[..., None]).sum(-1) / rho.sum(),
                torch.tensor([a * DEG], dtype=torch.float64), 128, 128)
        assert abs(float(d) - 1) < 0.015, (a, float(d))  # band-summed DHR / band-summed ρ


def test_brdf_elm_removes_the_lambertian_panel_error():
    mats_scene = panel_scene(sun_az=75.0)
    mats_scene.materials["white"] = Material("spectralon", panel="white", brdf=True)
    mats_scene.materials["dark"] = Material("spectralon", panel="dark", brdf=True)
    truth = torch.tensor([0.2, 0.37, 0.55, 0.8])
    sens = Sensor(noise=False, quantize=False)
    brdf = render(mats_scene, sensor=sens, elm="brdf", dtype=torch.float64)
    px = mesh_pixels(brdf, "target")
    assert float((brdf.reflectance[0, 0][px] - truth.double()).abs().max()) < 1e-4
    dhr = render(mats_scene, sensor=sens, elm="dhr", dtype=torch.float64)
    err = dhr.reflectance[0, 0][px].median(dim=0).values / truth.double() - 1
    # the panels read ~4 % (VIS) / ~7 % (NIR) darker than their DHR at 75° incidence, so the target reads
    # brighter by about as much (the exact figure depends on each panel's view angle through the lobe)
    assert 0.03 < float(err[:2].min()) and float(err[:2].max()) < 0.07
    assert 0.06 < float(err[2:].min()) and float(err[2:].max()) < 0.12


def test_pixel_subset_render_matches_full_frame_with_ideal_sensor():
    sc = panel_scene(sun_az=30.0, extra=[MeshSpec("ball", "sphere", "skin", params={"radius": 0.3},
                                                 position=[1.0, 0.0, 1.4])])
    sc.suns = [Sun(zenith_deg=90.0, azimuth_deg=a) for a in (10.0, 40.0)]
    full = render(sc, sensor=Sensor(noise=False, quantize=False, integration_time_s=1e-4))
    idx = full.gbuffer.hit[0].flatten().nonzero().flatten()[::7]
    sub = render_pixels(sc, idx, sensor=Sensor(noise=False, quantize=False, integration_time_s=1e-4))
    assert sub.reflectance.shape == (2, 1, 1, len(idx), 4)
    torch.testing.assert_close(sub.reflectance[:, 0, 0], full.reflectance[:, 0].flatten(1, 2)[:, idx])
    torch.testing.assert_close(sub.ndsi[:, 0, 0], full.ndsi[:, 0].flatten(1)[:, idx], equal_nan=True)


@pytest.mark.slow
def test_several_skins_in_one_batch_match_one_render_per_skin():
    sc = panel_scene(sun_az=25.0, extra=[MeshSpec("ball", "sphere", "skin", params={"radius": 0.3},
                                                 position=[1.0, 0.0, 1.4])])
    sc.suns = [Sun(zenith_deg=90.0, azimuth_deg=a, sky_fraction=0.1) for a in (10.0, 50.0)]
    sens = Sensor(noise=False, quantize=False)
    skins = ["I-II", {"melanosome": 0.3, "blood": 1.2}]
    both = render(sc, sensor=sens, skins=skins)
    assert both.reflectance.shape[0] == 4  # skin-major: (skin 0: 2 suns, skin 1: 2 suns)
    for k, sk in enumerate(skins):
        sc.materials["skin"] = Material("skin", skin=sk)
        one = render(sc, sensor=sens)
        torch.testing.assert_close(both.radiance[2 * k:2 * k + 2], one.radiance)
        torch.testing.assert_close(both.reflectance[2 * k:2 * k + 2], one.reflectance)


@pytest.mark.parametrize("shape", [(2, 1, 4096, 4), (1, 2, 1001, 4), (3, 1, 50, 3),  # full 64-wide rows + a tail
                                   (3, 2, 1, 4), (3, 2, 5, 4), (3, 2, 16, 4), (3, 2, 17, 4)])  # none, one, one + 1
def test_band_max_equals_amax(shape):
    """``sensor.band_max`` (the auto-exposure's frame maximum, reduced as 64-wide rows) is ``amax`` over the
    pixels, for negative values too (sensor noise), whole rows or not, contiguous or strided."""
    from torchskin.render.sensor import band_max

    x = torch.randn(shape, generator=torch.Generator().manual_seed(sum(shape))) - 1.0
    assert torch.equal(band_max(x), x.amax(dim=2))
    assert torch.equal(band_max(x.transpose(0, 1).contiguous().transpose(0, 1)), x.amax(dim=2))  # strided input


@pytest.mark.parametrize("skins", [None, ["I-II", {"melanosome": 0.3, "blood": 1.2}]])
def test_dense_shading_equals_gathered_shading(skins):
    """The sync-free shading of accelerators (BRDFs evaluated on every pixel, then selected) gives the CPU's
    gathered result: skin glints and Spectralon-BRDF panels under several suns, one or several skins."""
    from torchskin.render.light import light_tables
    from torchskin.render.materials import compile_materials, skin_batch
    from torchskin.render.raycast import Raycaster, rasterize
    from torchskin.render.shade import shade

    sc = panel_scene(sun_az=25.0, extra=[MeshSpec("ball", "sphere", "skin", params={"radius": 0.3},
                                                 position=[1.0, 0.0, 1.4])])
    sc.materials["white"] = Material("spectralon", panel="white", brdf=True)
    sc.suns = [Sun(zenith_deg=z, azimuth_deg=a, sky_fraction=0.1) for z, a in ((90.0, 10.0), (50.0, -40.0), (20.0, 70.0))]
    gb = rasterize(sc)
    gb = Raycaster.from_scene(sc).with_sky_view(gb)
    reps = 1 if skins is None else len(skins)
    tables = compile_materials(sc.materials, sc.bands, sc.suns, gb.material_names, torch.float64,
                               skins=None if skins is None else skin_batch(skins))
    light = light_tables(sc.illumination, sc.suns, sc.bands).repeat(reps)
    assert tables.groups["skin-thesis"].ids == (gb.material_names.index("skin"),)
    assert tables.groups["spectralon-brdf"].ids == (gb.material_names.index("white"),)
    gb = gb.to(dtype=torch.float64)
    if skins is not None:
        gb.shadow = gb.shadow.repeat(reps, 1, 1, 1)
    dirs = torch.tensor(np.stack([s.direction for s in sc.suns]), dtype=torch.float64).repeat(reps, 1)
    gathered, dense = shade(gb, tables, light, dirs, dense=False), shade(gb, tables, light, dirs, dense=True)
    torch.testing.assert_close(dense.radiance, gathered.radiance, rtol=1e-12, atol=0)
    assert torch.equal(dense.lit, gathered.lit)
    ball = (gb.mesh[0] == gb.mesh_names.index("ball")).flatten()
    assert ball.sum() > 50 and bool((gathered.radiance[:, 0].flatten(1, 2)[:, ball] > 0).any())


def test_sky_background_reads_the_sky_through_elm():
    """With background="sky", rays that escape above the horizon see the uniform sky dome, radiance
    f·E/π; through ELM on camera-facing Lambertian panels (normal n, lit by the sun s and the dome they see, V ≈
    (1 + n_z) / 2) that reads f / (n·s + f V) in every band. Rays escaping below the horizon stay black, and the default
    "void" background leaves every missed pixel without radiance."""
    f, zen = 0.2, 60.0
    sc = panel_scene(sun_zen=zen, sky=f)
    sc.background = "sky"
    assert Scene.from_json(sc.to_json()).background == "sky"
    res = render(sc, sensor=None, dtype=torch.float64)
    gb = res.gbuffer
    miss = ~gb.hit[0]
    up, down = miss & (gb.view[0, ..., 2] < 0), miss & (gb.view[0, ..., 2] > 0)
    assert up.sum() > 100 and down.sum() > 100
    n_dot_s = math.sin(zen * DEG)  # panel normal +x (towards the camera), sun at azimuth 0
    # the vertical panels see half the dome: each its shared view by hemisphere rays, within the ray count of 1/2
    W = gb.hit.shape[-1]
    views, refs = [], []
    for k, p in enumerate(sc.panels):
        v = gb.sky[0].reshape(-1)[res.panel_pixels[k][0]]
        assert bool((v == v[0]).all()) and abs(float(v[0]) - 0.5) <= 2 / SKY_RAYS, (p, W)
        views.append(float(v[0]))
        refs.append(float(sc.materials[sc.mesh(p).material].reflectance))
    # the empirical line through the two panels' readings ρ (n·s + f V) (in units of E / π), at the sky's f
    (rw, rd), (vw, vd) = refs, views
    lw, ld = rw * (n_dot_s + f * vw), rd * (n_dot_s + f * vd)
    expected = rd + (f - ld) * (rw - rd) / (lw - ld)
    torch.testing.assert_close(res.reflectance[0, 0][up], torch.full_like(res.reflectance[0, 0][up], expected))
    assert float(res.radiance[0, 0][down].abs().max()) == 0.0
    sc.background = "void"
    assert float(render(sc, sensor=None).radiance[0, 0][miss].abs().max()) == 0.0
    with pytest.raises(ValueError, match="background"):
        sc.background = "stars"
        sc.__post_init__()


def test_panel_pixels_found_once_give_the_same_frames():
    """``render(..., panel_pixels=...)`` and ``render_pixels(..., panel_pixels=...)`` with the panels' interior found
    once give exactly the frames that find it themselves."""
    from torchskin.render.elm import panel_pixels

    sc = panel_scene(sun_az=30.0, extra=[MeshSpec("ball", "sphere", "skin", params={"radius": 0.3},
                                                 position=[1.0, 0.0, 1.4])])
    sens = Sensor(noise=True, seed=3)
    first = render(sc, sensor=sens)
    pix = panel_pixels(first.gbuffer, list(sc.panels))
    again = render(sc, sensor=sens, gbuffer=first.gbuffer, panel_pixels=pix)
    assert torch.equal(again.signal, first.signal) and torch.equal(again.reflectance, first.reflectance)
    idx = first.gbuffer.hit[0].flatten().nonzero().flatten()[::5]
    a = render_pixels(sc, idx, sensor=sens, gbuffer=first.gbuffer)
    b = render_pixels(sc, idx, sensor=sens, gbuffer=first.gbuffer, panel_pixels=pix)
    assert torch.equal(a.reflectance, b.reflectance)


@pytest.mark.anny
def test_anny_bodies_are_the_same_bits_alone_and_in_any_batch():
    """A dataset shard builds its bodies in one anny call (``meshes.anny_batch``); a body must not depend on the
    batch it was built in, or a group's rows would change with the shard layout."""
    from torchskin.render.meshes import anny_batch, anny_body

    bodies = [({"gender": g, "height": h}, {"head": [p, 0.0, y]})
              for g, h, p, y in ((0.2, 0.7, -5.0, 10.0), (0.9, 0.3, 8.0, -25.0), (0.5, 0.5, 0.0, 40.0))]
    alone = [anny_body(ph, po, cache=False) for ph, po in bodies]
    with anny_batch(bodies):
        batched = [anny_body(ph, po, cache=False) for ph, po in bodies]
    with anny_batch(bodies[::-1] + bodies[:1] * 7):  # another order, another batch size
        shuffled = [anny_body(ph, po, cache=False) for ph, po in bodies]
    for a, b, c in zip(alone, batched, shuffled, strict=True):
        for x, y, z in zip(a, b, c, strict=True):
            assert np.array_equal(x, y) and np.array_equal(x, z)
    assert not np.array_equal(alone[0][0], alone[1][0])  # different bodies
    with anny_batch(bodies[:1]):
        pass
    from torchskin.render.meshes import _PREBUILT

    assert not _PREBUILT  # released when the block ends
