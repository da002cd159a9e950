"""The renderer's per-pixel kernels (``render.kernels``): compiled and eager paths agree, the noise draw is the
same, one compilation serves every frame size, the eager fallback without a compiler; shadow rays only where
they matter; helpers (band tiles, vertex normals; ``sensor.band_max`` is tested in test_render.py)."""

import math
import warnings

import numpy as np
import pytest
import torch

from torchskin.compiled import KernelCache
from torchskin.detect import DEFAULT_BOX, RulesBox, rules_detector
from torchskin.devices import compiler_problem
from torchskin.render import kernels
from torchskin.render.kernels import KERNELS, band_tiles, compiler_available, tile
from torchskin.render.meshes import vertex_normals
from torchskin.render.pipeline import render, render_pixels
from torchskin.render.raycast import Raycaster
from torchskin.render.scene import Camera, Material, MeshSpec, Scene, Sun
from torchskin.render.sensor import Sensor

needs_compiler = pytest.mark.skipif(not compiler_available("cpu"), reason=f"no compiled CPU kernels here: "
                                                                         f"{compiler_problem('cpu')}")
slow = pytest.mark.slow  # compiles (seconds to tens of seconds with a cold Inductor cache)


def scene(width=48, height=40, suns=2, sky_background=True):
    """A skin sphere (smooth normals, the skin BRDF), BRDF panels, a Lambertian ground, sky, several suns."""
    mats = {"skin": Material("skin", skin="IV"), "ground": Material("lambertian", reflectance=[0.15, 0.2, 0.3, 0.25]),
            "white": Material("spectralon", panel="white", brdf=True),
            "dark": Material("spectralon", panel="dark", brdf=True)}
    meshes = [MeshSpec("ball", "sphere", "skin", params={"radius": 0.45, "subdivisions": 4}, position=[0, 0, 1.0]),
              MeshSpec("panel_white", "plane", "white", params={"width": 0.35, "height": 0.35}, position=[0.3, 0.75, 0.6]),
              MeshSpec("panel_dark", "plane", "dark", params={"width": 0.35, "height": 0.35}, position=[0.3, -0.75, 0.6]),
              MeshSpec("ground", "ground", "ground")]
    cam = Camera(width=width, height=height, zenith_deg=80.0, range_m=9.449, target=[0, 0, 1.0], fov_deg=16.0)
    sun_list = [Sun(zenith_deg=35.0 + 15 * k, azimuth_deg=20.0 - 50 * k, sky_fraction=0.1) for k in range(suns)]
    return Scene(mats, meshes, [cam], sun_list, background="sky" if sky_background else "void")


def close(a: torch.Tensor, b: torch.Tensor, rtol: float = 1e-5) -> float:
    """Largest |a - b| relative to the frame's largest |b| per band (NaNs must match)."""
    assert torch.equal(torch.isnan(a), torch.isnan(b))
    a, b = torch.nan_to_num(a), torch.nan_to_num(b)
    scale = b.abs().flatten(0, -2).amax(0).clamp_min(1e-30) if b.dim() > 1 else b.abs().max().clamp_min(1e-30)
    return float(((a - b).abs() / scale).max())


def mask_differs_off_edges(a: torch.Tensor, b: torch.Tensor, ndgri: torch.Tensor, ndsi: torch.Tensor,
                           box: RulesBox, eps: float) -> torch.Tensor:
    """Pixels where rules masks ``a`` and ``b`` differ although neither index lies within ``eps`` of an edge
    of ``box`` (the box the masks were made with: its edges come from it, not from copies of its numbers)."""
    near_g = ((ndgri[..., None] - torch.tensor([box.b1, box.b2])).abs() < eps).any(-1)
    near_s = ((ndsi[..., None] - torch.tensor([box.c1, box.c2])).abs() < eps).any(-1)
    return (a != b) & ~(near_g | near_s)


def test_mask_edge_exemption_uses_the_detectors_box():
    """The exemption above: a flip at each of the box's edges is excused, one 1e-3 inside it is not."""
    box = DEFAULT_BOX
    g = torch.tensor([box.b1, box.b2, -0.3, -0.3, -0.3, -0.3])
    s = torch.tensor([0.7, 0.7, box.c1, box.c2, box.c2 - 1e-3, 0.7])
    a = rules_detector(g, s, box)
    flipped = ~a
    assert mask_differs_off_edges(flipped, a, g, s, box, 1e-5).tolist() == [False] * 4 + [True, True]


@slow
@needs_compiler
def test_compiled_frame_equals_eager_without_noise():
    sc = scene()
    sensor = Sensor(noise=False, quantize=False)
    eager = render(sc, sensor=sensor, elm="brdf", box=DEFAULT_BOX, compile=False)
    comp = render(sc, sensor=sensor, elm="brdf", box=DEFAULT_BOX, compile=True)
    gb_e, gb_c = eager.gbuffer, comp.gbuffer
    for f in ("hit", "material", "mesh", "shadow"):
        assert torch.equal(getattr(gb_e, f), getattr(gb_c, f)), f
    hit = gb_e.hit[0]
    assert close(gb_c.normal[0][hit], gb_e.normal[0][hit]) < 1e-5
    assert int((eager.skin[0]).sum()) > 100 and 0 < int(eager.lit.sum()) < eager.lit.numel()  # skin, shadows
    for f in ("radiance", "signal", "reflectance"):
        assert close(getattr(comp, f), getattr(eager, f)) < 1e-5, f
    assert torch.equal(comp.lit, eager.lit)
    # (a - b) / (a + b) moves by at most (2b|da| + 2a|db|) / (a + b)^2 <= 2(|da| + |db|) / (a + b) when a and b
    # move by da and db: each index within that bound of the measured reflectance differences (+ float32 rounding)
    for f, (i, j) in (("ndgri", (0, 1)), ("ndsi", (2, 3))):
        a, b = eager.reflectance[..., i], eager.reflectance[..., j]
        da, db = (comp.reflectance[..., i] - a).abs(), (comp.reflectance[..., j] - b).abs()
        bound = 2 * (da + db) / (a + b).abs() + 1e-6
        diff = (getattr(comp, f) - getattr(eager, f)).abs()
        assert bool(((diff <= bound) | diff.isnan()).all()), f
    # the rules mask may differ only where an index sits within 1e-5 (the indices' agreement above) of an edge
    assert not mask_differs_off_edges(comp.mask, eager.mask, eager.ndgri, eager.ndsi, DEFAULT_BOX, 1e-5).any()


@slow
@needs_compiler
def test_compiled_noise_draw_is_the_eager_one():
    sc = scene(suns=1)
    sensor = Sensor(noise=True, quantize=False, seed=11)
    eager = render(sc, sensor=sensor, compile=False)
    comp = render(sc, sensor=sensor, compile=True)
    clean = render(sc, sensor=Sensor(noise=False, quantize=False), compile=False)
    noise = eager.signal - clean.signal
    assert float(noise.std()) > 1.0  # the noise is there (DN)...
    assert close(comp.signal, eager.signal) < 1e-5  # ...and it is the same draw
    other = render(sc, sensor=Sensor(noise=True, quantize=False, seed=12), compile=True)
    assert float((other.signal - eager.signal).abs().max()) > 5 * float(noise.std())
    quantized = Sensor(noise=True, seed=11)
    dn_e, dn_c = render(sc, sensor=quantized).signal, render(sc, sensor=quantized, compile=True).signal
    assert float((dn_e - dn_c).abs().max()) <= 1.0  # rounding may move a DN by one, never more


@slow
@needs_compiler
def test_one_compilation_serves_every_frame_size():
    sensor = Sensor(noise=False)
    render(scene(48, 40, suns=1), sensor=sensor, compile=True)
    render(scene(64, 36, suns=1), sensor=sensor, compile=True)
    graphs = torch._dynamo.utils.counters["stats"]["unique_graphs"]
    for w, h in ((80, 50), (32, 32), (96, 24)):
        res = render(scene(w, h, suns=1), sensor=sensor, compile=True)
        assert res.radiance.shape == (1, 1, h, w, 4)
    assert torch._dynamo.utils.counters["stats"]["unique_graphs"] == graphs


@slow
@needs_compiler
def test_no_recompilation_across_pose_groups():
    """Groups with other confuser counts (meshes, materials) and other sensor settings (read noise) reuse the
    compiled kernels: scene-sized tables are padded (``kernels.table_rows``), scalars are tensor inputs, each BRDF
    kind is a kernel of its own."""
    import tempfile

    from torchskin.dataset.config import resolve_config
    from torchskin.dataset.generate import generate

    cfg = resolve_config({"camera": {"width": 48, "height": 48}, "sun": {"per_pose": 2}, "skin": {"per_pose": 1},
                          "sampling": {"groups_per_shard": 1, "pixels_per_class": 16}, "confusers": {"count": [0, 4]},
                          "sensor": {"read_noise_e": [10.0, 200.0]}})
    with tempfile.TemporaryDirectory() as d:
        generate(cfg, 2 * 4, 7, f"{d}/warm", quiet=True, compile=True)  # every material kind, some confuser counts
        graphs = torch._dynamo.utils.counters["stats"]["unique_graphs"]
        man = generate(cfg, 2 * 6, 8, f"{d}/run", quiet=True, compile=True)
    assert man["compiled"] and torch._dynamo.utils.counters["stats"]["unique_graphs"] == graphs


def test_scene_sized_tables_are_padded_past_the_static_axes():
    from torchskin.render.kernels import TABLE_ROWS, pad_rows, table_rows

    assert table_rows(5) == table_rows(17) == TABLE_ROWS > 16 and table_rows(TABLE_ROWS + 1) == 2 * TABLE_ROWS
    x = torch.arange(24.0).reshape(2, 3, 4)
    y = pad_rows(x)
    assert y.shape == (2, TABLE_ROWS, 4) and torch.equal(y[:, :3], x) and not y[:, 3:].any()
    assert pad_rows(y) is y


@slow
@needs_compiler
def test_compiled_pixel_render_with_a_skin_batch_equals_eager():
    sc = scene(suns=3)
    rc = Raycaster.from_scene(sc)
    gb = rc.gbuffer(sc.cameras, np.stack([s.direction for s in sc.suns]), shadows=False)
    px = torch.arange(0, gb.hit.numel(), 7)
    kw = dict(sensor=Sensor(noise=True, quantize=False, seed=2), gbuffer=gb, raycaster=rc, skins=["I-II", "V-VI"])
    eager, comp = render_pixels(sc, px, **kw), render_pixels(sc, px, compile=True, **kw)
    assert eager.reflectance.shape == (6, 1, 1, len(px), 4)
    for f in ("radiance", "signal", "reflectance"):
        assert close(getattr(comp, f), getattr(eager, f)) < 1e-5, f


def test_fallback_without_compiler_is_the_eager_path(monkeypatch):
    monkeypatch.setattr("torchskin.compiled.compiler_problem", lambda device="cpu": "no compiler here")
    local = KernelCache()
    with pytest.warns(RuntimeWarning, match="eagerly"):
        fn = local.get(kernels.elm_line, True)
    assert fn is kernels.elm_line
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # warned once per device, not per call or kernel
        assert local.get(kernels.elm_line, True) is kernels.elm_line
        assert local.get(kernels.sensor_dn, True) is kernels.sensor_dn
    monkeypatch.setattr(kernels, "KERNELS", local)
    monkeypatch.setattr("torchskin.render.shade.KERNELS", local)
    monkeypatch.setattr("torchskin.render.sensor.KERNELS", local)
    monkeypatch.setattr("torchskin.render.raycast.KERNELS", local)
    monkeypatch.setattr("torchskin.render.pipeline.KERNELS", local)
    sc = scene(suns=1)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # one warning per device, already given
        fallback = render(sc, sensor=Sensor(seed=4), compile=True)
    eager = render(sc, sensor=Sensor(seed=4))
    assert torch.equal(fallback.signal, eager.signal) and torch.equal(fallback.reflectance.nan_to_num(), eager.reflectance.nan_to_num())


def test_compile_failure_falls_back_with_a_warning(monkeypatch):
    local = KernelCache()
    monkeypatch.setattr("torchskin.compiled.compiler_problem", lambda device="cpu": None)

    def broken(fn, **kw):
        def run(*a):
            raise RuntimeError("inductor exploded")
        return run

    monkeypatch.setattr(torch, "compile", broken)
    x = torch.rand(3, 4)
    with pytest.warns(RuntimeWarning, match="inductor exploded"):
        out = local.get(kernels.elm_line, True)(x, torch.full((4,), 2.0), torch.zeros(4))
    assert torch.equal(out, kernels.elm_line(x, torch.full((4,), 2.0), torch.zeros(4)))


@slow
def test_shadow_rays_only_where_a_pixel_faces_the_sun():
    sc = scene(suns=2, sky_background=False)
    rc = Raycaster.from_scene(sc)
    dirs = np.stack([s.direction for s in sc.suns])
    gb = rc.gbuffer(sc.cameras, dirs)
    n = gb.normal[0].reshape(-1, 3)
    hit = gb.hit[0].reshape(-1)
    for s in range(len(dirs)):
        facing = (n @ torch.tensor(dirs[s], dtype=torch.float32) > 0) & hit
        shadow = gb.shadow[s, 0].reshape(-1)
        assert not (shadow & ~(n @ torch.tensor(dirs[s], dtype=torch.float32) > -1e-6)).any()
        # against every hit pixel's own shadow ray
        org = torch.addcmul(gb.position[0].reshape(-1, 3), gb.geometric_normal[0].reshape(-1, 3), torch.tensor(1e-3))
        rays = torch.cat([org[hit], torch.tensor(dirs[s], dtype=torch.float32).expand(int(hit.sum()), 3)], -1)
        brute = torch.zeros_like(hit)
        brute[hit] = rc.occluded(rays)
        assert torch.equal(shadow & facing, brute & facing)
        assert int((brute & facing).sum()) > 20  # the sphere shades the ground
    no_shadow = rc.gbuffer(sc.cameras, dirs, shadows=False)
    assert no_shadow.shadow is None
    assert torch.equal(rc.with_shadows(no_shadow, dirs).shadow, gb.shadow)


def test_pixel_render_casts_shadows_for_its_pixels_only():
    sc = scene(suns=2)
    rc = Raycaster.from_scene(sc)
    dirs = np.stack([s.direction for s in sc.suns])
    px = torch.arange(3, 48 * 40, 5)
    full = render_pixels(sc, px, gbuffer=rc.gbuffer(sc.cameras, dirs), raycaster=rc, sensor=Sensor(seed=1))
    lazy = render_pixels(sc, px, gbuffer=rc.gbuffer(sc.cameras, dirs, shadows=False), raycaster=rc, sensor=Sensor(seed=1))
    assert torch.equal(full.signal, lazy.signal) and torch.equal(full.lit, lazy.lit)
    with pytest.raises(ValueError, match="raycaster"):
        render_pixels(sc, px, gbuffer=rc.gbuffer(sc.cameras, dirs, shadows=False))


@pytest.mark.parametrize("pixels,bands", [(3072, 4), (1000, 4), (7, 4), (64, 5), (40, 16), (9, 20)])
def test_band_tiles_keep_every_value_with_its_band(pixels, bands):
    x = torch.rand(2, 3, pixels, bands)
    per = torch.rand(2, 3, bands)
    view, tiled, k = band_tiles(x, per)
    assert view.shape[-1] == k * bands and (pixels % k == 0) and view.shape[-1] <= max(16, bands)
    assert torch.equal((view * tiled).reshape(x.shape), x * per[:, :, None, :])
    c = torch.rand(bands)
    assert torch.equal((view * tile(c, k)).reshape(x.shape), x * c)


def test_vertex_normals_are_the_area_weighted_sums():
    rng = np.random.default_rng(0)
    v, f = rng.random((500, 3)), rng.integers(0, 500, (2000, 3))
    acc = np.zeros_like(v)
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    for k in range(3):
        np.add.at(acc, f[:, k], fn)
    expected = acc / np.linalg.norm(acc, axis=1, keepdims=True)
    assert np.array_equal(vertex_normals(v, f), expected.astype(np.float32))


def test_kernel_functions_keep_their_device_and_dtype(device):
    dtype = torch.float32
    sig = torch.rand(1, 1, 8, 8, 4, dtype=dtype, device=device) * 1000
    a = torch.full((1, 1, 4), 900.0, dtype=dtype, device=device)
    b = torch.full((1, 1, 4), 12.0, dtype=dtype, device=device)
    view, ta, k = band_tiles(sig, a)
    refl, g, s, rules = KERNELS.get(kernels.elm_indices, False, device)(
        view, ta, b.reshape(1, 1, 4).repeat(1, 1, k), 4, (0, 1, 2, 3), kernels.RulesBox())
    assert refl.device.type == device.type and refl.dtype == dtype and g.shape == (64,)
    assert torch.allclose(refl.reshape(sig.shape), (sig - 12.0) / 900.0, rtol=1e-6)
    assert math.isclose(float(g[0]), float((refl.reshape(-1, 4)[0, 0] - refl.reshape(-1, 4)[0, 1])
                                            / (refl.reshape(-1, 4)[0, 0] + refl.reshape(-1, 4)[0, 1])), rel_tol=1e-6)


def test_one_kernel_cache_writes_no_environment(monkeypatch, tmp_path):
    """The skin model and the renderer share one compiled-kernel cache, and torchskin writes no environment
    variable (Inductor's cache folder is the user's TORCHINDUCTOR_CACHE_DIR or Inductor's default; torch.compile
    itself, stubbed here, records its default there)."""
    import os

    from torchskin import compiled, tissue
    from torchskin.devices import inductor_cache_dir

    assert kernels.KERNELS is compiled.KERNELS
    assert tissue._evaluate.__globals__["KERNELS"] is compiled.KERNELS
    monkeypatch.setattr("torchskin.compiled.compiler_problem", lambda device="cpu": None)
    monkeypatch.setattr(torch, "compile", lambda fn, **kw: fn)
    monkeypatch.delenv("TORCHINDUCTOR_CACHE_DIR", raising=False)
    before = dict(os.environ)
    local = KernelCache()
    local.get(kernels.elm_line, True)  # compiled lazily: nothing runs yet
    assert len(local) == 1 and dict(os.environ) == before
    from torch._inductor.runtime.cache_dir_utils import default_cache_dir

    assert inductor_cache_dir() == os.path.abspath(default_cache_dir())
    monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", str(tmp_path / "mine"))
    assert inductor_cache_dir() == str(tmp_path / "mine") and str(kernels.cache_dir()) == str(tmp_path / "mine")
