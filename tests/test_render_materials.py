"""The material registry (``render.materials``): a new kind is one entry, skins compile as one batch, and compiled
tables are never stale after ``data.register_table``. Also: the scene stage is plain data (no torch)."""

import subprocess
import sys

import pytest
import torch

from torchskin import data, tissue
from torchskin.render import materials as M
from torchskin.render.pipeline import render
from torchskin.render.scene import Camera, Material, MeshSpec, Scene, Sun

DT = torch.float64


def wall_scene(material: Material, name: str = "wall") -> Scene:
    """A wall of ``material`` (named ``name``) facing a horizontal camera, two Lambertian panels in front of it."""
    mats = {name: material, "white": Material(reflectance=0.97), "dark": Material(reflectance=0.03)}
    meshes = [MeshSpec("wall", "plane", name, {"width": 6.0, "height": 6.0}, position=[-1.0, 0.0, -2.0]),
              MeshSpec("panel_white", "plane", "white", {"width": 0.4, "height": 0.4}, position=[0.0, 0.5, 0.8]),
              MeshSpec("panel_dark", "plane", "dark", {"width": 0.4, "height": 0.4}, position=[0.0, -0.5, 0.8])]
    return Scene(mats, meshes, [Camera(width=48, height=48, target=[0.0, 0.0, 1.0], fov_deg=20.0)],
                 [Sun(zenith_deg=50.0, azimuth_deg=20.0)], illumination="thesis")  # the sun alone: ELM is exact


def test_a_new_material_kind_is_one_registry_entry():
    """A toy kind, a Lambertian whose albedo rises linearly with wavelength, registered here without touching any
    torchskin module: the renderer shades it, and ELM on an ideal sensor reads its albedo back in every band."""

    def compile_ramp(material, spectral, skins):
        lo, hi = material.params["albedo_at_400nm"], material.params["albedo_at_1700nm"]
        return M.Compiled(albedo=(lo + (hi - lo) * (spectral.wavelengths - 400.0) / 1300.0)[None])

    M.register("ramp", M.MaterialKind(compile=compile_ramp))
    try:
        sc = wall_scene(Material("ramp", params={"albedo_at_400nm": 0.1, "albedo_at_1700nm": 0.75}))
        res = render(sc, dtype=DT)
        wall = res.gbuffer.hit[0] & (res.gbuffer.mesh[0] == res.gbuffer.mesh_names.index("wall")) & res.lit[0, 0]
        expect = torch.tensor([0.1 + 0.65 * (c - 400.0) / 1300.0 for c in (544.0, 633.0, 1080.0, 1580.0)], dtype=DT)
        assert int(wall.sum()) > 500
        torch.testing.assert_close(res.reflectance[0, 0][wall], expect.expand(int(wall.sum()), 4), rtol=1e-9, atol=1e-9)
        # with a BRDF too: a kind whose BRDF is twice the Lambertian value reads twice the albedo
        M.register("ramp", M.MaterialKind(compile=lambda m, sp, sk: M.Compiled(albedo=torch.full((1, 4), 0.2, dtype=DT),
                                                                             params={"rho": torch.full((1, 4), 0.2, dtype=DT)}),
                                          brdf=lambda ci, cr, c2b, p: (2 / torch.pi) * p["rho"] * (ci > 0)))
        lit = render(sc, dtype=DT).reflectance[0, 0][wall]
        # ELM reads radiance in Lambertian units: sun term doubled, sky term (albedo) unchanged
        assert float(lit.min()) > 0.3 and float(lit.max()) < 0.4
    finally:
        M.unregister("ramp")
    with pytest.raises(ValueError, match="material kind must be one of"):
        render(wall_scene(Material("ramp")))


def test_registry_errors_name_the_material_parameter():
    for material, match in ((Material("lambertian"), "needs reflectance"),
                            (Material("lambertian", reflectance=1.5), r"\[0, 1\]"),
                            (Material("spectralon", panel="grey"), "white' or 'dark"),
                            (Material("skin", skin="VII"), "unknown preset"),
                            (Material("skin", surface="shiny"), "surface must be one of"),
                            (Material("lambertian", reflectance=0.5, brdf=True), "brdf=True")):
        with pytest.raises(ValueError, match=match):
            M.check_material(material)
    assert M.kind_name(Material("skin", specular=False)) == "skin-diffuse"
    assert M.kind_name(Material("spectralon", panel="white", brdf=True)) == "spectralon-brdf"


def test_batched_skins_compile_as_one_per_skin():
    """16 skins compiled as one ``SkinParams`` batch give each skin's own tables (the batch's rows are skin-major,
    one per sun)."""
    sc = wall_scene(Material("skin", skin="I-II"), name="skin")
    sc.suns = [Sun(zenith_deg=30.0), Sun(zenith_deg=60.0, azimuth_deg=40.0)]
    batch, _ = tissue.sample(16, 4, dtype=DT)
    values = batch.as_dict()
    tables = M.compile_materials(sc.materials, sc.bands, sc.suns, dtype=DT, skins=batch)
    skin = list(sc.materials).index("skin")
    assert tables.albedo.shape == (32, 3, 4)
    for k in (0, 7, 15):
        one = M.compile_materials({**sc.materials, "skin": Material("skin", skin={n: v[k] for n, v in values.items()})},
                                  sc.bands, sc.suns, dtype=DT)
        r_sub = one.groups["skin-thesis"].params["r_sub"]  # one skin: a row shared by the group, (B,)
        assert r_sub.shape == (4,)
        for row in (2 * k, 2 * k + 1):
            torch.testing.assert_close(tables.albedo[row], one.albedo, rtol=1e-12, atol=0)
            torch.testing.assert_close(tables.groups["skin-thesis"].params["r_sub"][row, skin], r_sub, rtol=1e-12,
                                       atol=0)
    assert tables.groups["skin-thesis"].params["sigma2"].shape == (4,)  # the same for every skin: not gathered


def test_renderer_never_serves_tables_of_a_replaced_data_table():
    """Tripled water absorption darkens rendered skin at 1580 nm at once, through a ``MaterialCache`` too; the
    packaged table restores the frame exactly."""
    sc = wall_scene(Material("skin", skin="I-II"))
    cache = M.MaterialCache()
    before = render(sc, dtype=DT, cache=cache).radiance
    _, water = data.table("water_segelstein")
    try:
        data.register_table("water_segelstein", water[:, 0], 3 * water[:, 1])
        tripled = render(sc, dtype=DT, cache=cache).radiance
    finally:
        data.unregister_table("water_segelstein")
    wall = before[0, 0, ..., 3] > 0
    assert float(tripled[0, 0, ..., 3][wall].sum()) < 0.9 * float(before[0, 0, ..., 3][wall].sum())
    torch.testing.assert_close(tripled[..., :2], before[..., :2], rtol=5e-3, atol=0)  # visible: water barely matters
    assert torch.equal(render(sc, dtype=DT, cache=cache).radiance, before)


def test_scene_stage_imports_neither_torch_nor_the_skin_model():
    code = ("import sys, torchskin.render.scene as s; sc = s.default_scene(subject='file', mesh_path='x.obj'); "
            "assert s.Scene.from_json(sc.to_json()) == sc; "
            "print(sorted(m for m in ('torch', 'torchskin.tissue', 'numpy') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "['numpy']"


def test_material_cache_keeps_tables_by_what_they_depend_on():
    """The same materials, bands and suns give the kept tables (the same object); a changed material, band,
    dtype or sun spectrum compiles anew; ``clear`` forgets."""
    sc = wall_scene(Material("skin", skin="I-II"))
    cache = M.MaterialCache()
    first = cache.compile(sc.materials, sc.bands, sc.suns)
    assert cache.compile(sc.materials, sc.bands, sc.suns) is first
    darker = {**sc.materials, "wall": Material("skin", skin="V-VI")}
    assert cache.compile(darker, sc.bands, sc.suns) is not first
    assert cache.compile(sc.materials, sc.bands, sc.suns, dtype=DT) is not first
    assert cache.compile(sc.materials, sc.bands, [Sun(temperature_k=3000.0)]) is not first
    assert cache.compile(sc.materials, sc.bands[:2], sc.suns).albedo.shape == (3, 2)
    assert len(cache.entries) == 5
    cache.clear()
    assert cache.compile(sc.materials, sc.bands, sc.suns) is not first
    skin_rows = first.albedo[list(sc.materials).index("wall")]
    assert bool((cache.compile(darker, sc.bands, sc.suns).albedo[0] < skin_rows).all())  # V-VI darker than I-II


def test_default_scene_takes_any_subject_mesh():
    """``default_scene(subject=MeshSpec(...))``: a skin sphere where the camera aims, no mesh file needed."""
    from torchskin.render.scene import default_scene

    ball = MeshSpec("subject", "sphere", "skin", {"radius": 0.3, "subdivisions": 3}, position=[0.0, 0.0, 1.0])
    sc = default_scene(subject=ball, camera=Camera(width=48, height=48))
    assert Scene.from_json(sc.to_json()) == sc
    res = render(sc)
    assert int(res.skin[0].sum()) > 40 and bool(res.mask[0, 0][res.skin[0] & res.lit[0, 0]].any())
    with pytest.raises(ValueError, match="subject must be"):
        default_scene(subject="cube")


def test_review_edge_cases_fail_early_with_one_line():
    """Variants are chosen by fields, not written as kinds; unknown kinds list the registered names in full;
    per-band values are checked against the scene's bands before any geometry; skins must be a batch or a list;
    a skins batch needs a skin material named "skin"."""
    from torchskin.bands import DEFAULT_BANDS

    with pytest.raises(ValueError, match="specular=False"):
        M.check_material(Material("skin-diffuse", skin="I-II"))
    with pytest.raises(ValueError, match="brdf=True"):
        M.check_material(Material("spectralon-brdf", panel="white"))
    M.register("grey-ramp", M.MaterialKind(compile=lambda m, sp, sk: M.Compiled(albedo=torch.ones(1, 4))))
    try:
        with pytest.raises(ValueError, match="grey-ramp, lambertian, rtlsr, skin, spectralon, got 'plaster'"):
            M.check_material(Material("plaster"))
    finally:
        M.unregister("grey-ramp")
    with pytest.raises(ValueError, match="material 'wall': a lambertian reflectance needs one value"):
        M.check_materials({"wall": Material("lambertian", reflectance=[0.1, 0.2, 0.3])}, DEFAULT_BANDS)
    M.check_materials({"wall": Material("lambertian", reflectance=(0.1, 0.2, 0.3, 0.4))}, DEFAULT_BANDS)
    with pytest.raises(ValueError, match="skins must be"):
        M.skin_batch("IV")
    sc = wall_scene(Material(reflectance=0.3), name="skin")
    sc.suns = [Sun(), Sun(zenith_deg=50.0)]
    with pytest.raises(ValueError, match="of kind 'skin'"):
        render(sc, skins=["I-II", "V-VI"])


def test_material_cache_takes_band_objects_and_keys_on_names():
    from torchskin.bands import DEFAULT_BANDS

    sc = wall_scene(Material("skin", skin="I-II"))
    cache = M.MaterialCache()
    a = cache.compile(sc.materials, DEFAULT_BANDS, sc.suns)
    assert cache.compile(sc.materials, sc.bands, sc.suns) is a  # Band objects and [centre, fwhm] pairs alike
    renamed = {f"m{k}": v for k, v in enumerate(sc.materials.values())}
    b = cache.compile(renamed, sc.bands, sc.suns)
    assert b is not a and b.names == list(renamed)
    assert M.SHARED_CACHE is not cache and isinstance(M.SHARED_CACHE, M.MaterialCache)


def test_write_outputs_takes_a_scene_or_its_dict(tmp_path):
    from torchskin.render.outputs import write_outputs

    sc = wall_scene(Material(reflectance=0.3))
    res = render(sc)
    write_outputs(res, sc, tmp_path / "a")
    write_outputs(res, sc.to_dict(), tmp_path / "b")
    assert (tmp_path / "a" / "render.json").read_text().split('"scene"')[1] == \
        (tmp_path / "b" / "render.json").read_text().split('"scene"')[1]
    with pytest.raises(TypeError, match="scene must be"):
        write_outputs(res, "scene.json", tmp_path / "c")
    assert not (tmp_path / "c").exists()
