"""The ``lut`` detector kind (issue 40): table geometry, the bake, the budgets, checkpoints, and the same decisions
from torch, the exported graph (onnxruntime) and the onboard numpy head."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from torchskin.bands import BandSet
from torchskin.cli import main
from torchskin.detectors import registry
from torchskin.detectors.features import DIFFUSE_SHARE, FEATURES
from torchskin.detectors.lut import LookupModel
from torchskin.detectors.lut.grid import (
    OCTAVE,
    bits,
    cell_centres,
    cells,
    check_geometry,
    config_bins,
    coordinates,
    reflectance_of,
)
from torchskin.detectors.lut.model import EVEN_ODDS_LEVEL, to_levels
from torchskin.detectors.lut.train import (
    EARTHLIB_SCALE,
    ENSEMBLE,
    SHADE_SHARE,
    SKY_VIEW,
    Skies,
    bake,
    earthlib_negatives,
    learn,
    learner_features,
    slice_centres,
    support,
    training_skies,
    tune_threshold,
)
from torchskin.detectors.protocol import CalibrationData

pytest.importorskip("lightgbm")


@pytest.mark.parametrize("n", [2, 3, 4, 5, 7])
def test_coordinates_describe_a_spectrum_completely(n):
    """The coordinates invert exactly (float32 reflectance back from integer bits), for any band count and any
    reference band; a factor of 16 moves the brightness axis by 4 octaves and no ratio axis at all."""
    R = torch.rand(500, n, generator=torch.Generator().manual_seed(n)) + 1e-3
    for ref in range(n):
        V = coordinates(R, ref)
        assert V.dtype == torch.int64
        assert torch.equal(reflectance_of(V.double(), ref).float(), R)
        V16 = coordinates(R * 16, ref)
        assert torch.equal(V16[:, 1:], V[:, 1:]) and torch.equal(V16[:, 0], V[:, 0] + 4 * OCTAVE)


def test_the_index_bands_coordinates_are_log2_ratios_of_neighbours():
    """Each ratio axis is log2 of a neighbouring bands' ratio, in 2^23 units an octave, within the piecewise-linear
    log's error (at most 0.0861 octave each way), and exact between powers of two."""
    R = torch.rand(2000, 4, generator=torch.Generator().manual_seed(1)) + 0.01
    V = coordinates(R, ref=0)  # the reference 544 nm: 633/544, 1080/633, 1580/1080
    for k, (i, j) in enumerate(((1, 0), (2, 1), (3, 2)), start=1):
        err = V[:, k].double() / OCTAVE - torch.log2(R[:, i].double() / R[:, j].double())
        assert err.abs().max() <= 0.0861
    P = torch.tensor([[0.25, 1.0, 0.5, 0.125]])
    assert (coordinates(P, ref=0) // OCTAVE).tolist() == [[125, 2, -1, -2]]  # 0.25 = 2^-2: 127 - 2


def test_cells_cut_each_axis_at_exact_edges_and_clip_outside():
    shift, lo, bins = torch.tensor([3, 0]), torch.tensor([1, -2]), 4  # cells of 8 units from 8; of 1 from -2
    V = torch.tensor([[8, -2], [15, -1], [16, 0], [39, 1], [-5, 7], [7, -3], [2 ** 40, -(2 ** 40)]])
    q0 = torch.tensor([0, 0, 1, 3, 0, 0, 3])
    q1 = torch.tensor([0, 1, 2, 3, 3, 0, 0])
    assert cells(V, shift, lo, bins).tolist() == (q0 * 4 + q1).tolist()
    assert cells(torch.tensor([[-1, -1]]), torch.tensor([3, 1]), torch.tensor([-1, -1]), 4).tolist() == [0]  # floors
    X = torch.tensor([[0.0, 10.0], [44.9, 10.0], [45.0, 100.0], [89.0, -1.0]])
    assert config_bins(X, torch.tensor([0.0, 0.0]), torch.tensor([2 / 90, 3 / 90]), (2, 3)).tolist() == [0, 0, 5, 3]


def test_centres_land_in_their_own_cells():
    m = LookupModel(4, 6, config_counts=(1, 1, 1))
    m.set_range(1, [21, 19, 20, 18], [240, -7, 3, -2])
    C = cell_centres(m.shift, m.lo, m.bins)
    assert torch.equal(m.cells_of(reflectance_of(C, m.ref).float()), torch.arange(6 ** 4))


def test_a_pixel_with_a_band_at_zero_negative_or_nan_lands_in_an_edge_cell():
    """Whatever the reference, such a pixel has an axis far outside its range (``check_geometry``): it is clipped
    into an edge cell, which the support never holds (no separate validity test exists or is needed)."""
    m = LookupModel(4, 8, config_counts=(1, 1, 1))
    bad = torch.tensor([[0.0, 0.2, 0.3, 0.1], [0.2, 0.1, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0], [1e-40, 0.2, 0.3, 0.1],
                        [0.2, -0.1, 0.3, 0.1], [0.2, float("nan"), 0.3, 0.1], [0.2, 0.1, 0.3, float("inf")]])
    good = torch.tensor([[0.2, 0.2, 0.25, 0.2]])
    for ref in range(4):  # brightness cells of 1/2 octave from 1/16, ratio cells of 1/4 octave from -1 octave
        m.set_range(ref, [22, 21, 21, 21], [(127 - 4) * 2, -4, -4, -4])
        q = torch.stack([(m.cells_of(torch.cat([good, bad])) // 8 ** (3 - k)) % 8 for k in range(4)], 1)
        edge = ((q == 0) | (q == 7)).any(1)
        assert not edge[0] and edge[1:].all(), (ref, q)
    with pytest.raises(ValueError, match="beyond"):
        check_geometry([20, 24, 20, 20], [900, -20, 0, 0], 8)  # 8 cells of 2 octaves from -40 octaves
    with pytest.raises(ValueError, match="below the normal floats"):
        check_geometry([20, 20, 20, 20], [0, -4, 0, 0], 8)


def test_the_graph_computes_float_bits_exactly_without_a_bit_cast():
    """``LookupDetector.float_bits`` (a logarithm corrected against exact powers of two, as the ONNX graph runs it)
    equals the float32 bit pattern at and next to every power of two, for subnormals, 0 and random values."""
    from torchskin.detectors.lut.model import LookupDetector

    p = torch.exp2(torch.arange(-149, 63, dtype=torch.float64)).float()
    x = torch.cat([p, torch.nextafter(p, torch.zeros(1)), torch.nextafter(p, torch.full((1,), 1e30)),
                   torch.rand(100000, generator=torch.Generator().manual_seed(0)) ** 4 * 8, torch.zeros(1)])
    assert torch.equal(LookupDetector(LookupModel()).float_bits(x), bits(x))


def ndsi_table(bins: int = 8) -> LookupModel:
    """A table baked from a known score: +4 log-odds where NDSI > 0.3, -4 elsewhere, the same in every slice."""
    m = LookupModel(4, bins, config_counts=(2, 1, 1))
    m.set_range(3, [23, 22, 22, 22], [127 - 6, -bins // 2, -bins // 2, -bins // 2])  # NDSI's ratio: axis 3

    def predict(f: np.ndarray) -> np.ndarray:
        ndsi = f[:, 4 + 5]  # the learner's features: 4 reflectances, then the pairs (0,1) (0,2) (0,3) (1,2) (1,3) (2,3)
        return np.where(ndsi > 0.3, 4.0, -4.0)

    bake(m, predict, torch.ones(bins ** 4, dtype=torch.bool))
    m.threshold.fill_(EVEN_ODDS_LEVEL + 1)
    return m


def test_a_baked_table_holds_its_score_at_every_cell_centre():
    m = ndsi_table()
    C = cell_centres(m.shift, m.lo, m.bins)
    R = reflectance_of(C, m.ref)
    ndsi = (R[:, 2] - R[:, 3]) / (R[:, 2] + R[:, 3])
    want = to_levels(torch.where(ndsi > 0.3, 4.0, -4.0))
    want = torch.where(want >= EVEN_ODDS_LEVEL, want, torch.zeros_like(want))  # below even odds: stored as 0
    for s in range(m.levels.shape[0]):
        assert torch.equal(m.levels[s], want)
    X = slice_centres(m).float()[torch.zeros(len(R), dtype=torch.long)]
    assert torch.equal(m.decide(R.float(), X), ndsi > 0.3)  # the rule at cell centres, decided from reflectance


def test_the_threshold_holds_the_earthlib_budget_in_every_slice_and_calibration_never_goes_below_it():
    m = ndsi_table()
    g = torch.Generator().manual_seed(0)
    spectra = torch.rand(1000, 4, generator=g) * 0.5 + 0.01
    thr = tune_threshold(m, spectra, 1e-3, None, None, None)
    hit = m.decide(spectra, slice_centres(m).float()[0].expand(1000, 3))
    # the NDSI > 0.3 cells hold level 160; with ~30 % of these spectra there, the threshold must pass above them
    assert float(hit.float().mean()) <= 1e-3 and thr == int(m.floor_level) == 161
    nonskin = torch.zeros(1000, dtype=torch.bool)
    data = CalibrationData(R=spectra, X=slice_centres(m).float()[0].expand(1000, 3), ndgri=torch.zeros(1000),
                           ndsi=torch.zeros(1000), ndvn=torch.zeros(1000), cfg_X=slice_centres(m).float(),
                           nonskin=nonskin, bright=torch.ones(1000, dtype=torch.bool), test_R=spectra,
                           test_bright=torch.ones(1000, dtype=torch.bool), test_pts=torch.zeros(1000, 3))
    rec = m.calibrate_to_budget(data, 1e-4, 1e-3)  # no non-skin rows: the floor level, not lower
    assert rec["after"] == 161


def test_the_support_leaves_out_every_edge_cell():
    m = LookupModel(4, 8, config_counts=(1, 1, 1))
    m.set_range(3, [23, 22, 22, 22], [127 - 6, -4, -4, -4])
    R = torch.tensor([[0.3, 0.25, 0.35, 0.2], [1.0, 0.0, 0.5, 0.5]])  # the second: a band at 0, in an edge cell
    where = support(m, R, 1).reshape(8, 8, 8, 8)
    q = [torch.div(m.cells_of(R), 8 ** (3 - k), rounding_mode="floor") % 8 for k in range(4)]
    q = torch.stack(q, 1)
    assert bool(where[tuple(q[0])]) and not bool(where[tuple(q[1])])
    for axis in range(4):
        assert not where.select(axis, 0).any() and not where.select(axis, 7).any()
    # the first pixel's cell dilated by one along every axis: a 3^4 cube; the second, in cell (5, 7, 0, 4), adds
    # its cube's cells off every edge: 3 x 1 x 1 x 3
    assert q.tolist() == [[3, 4, 3, 5], [5, 7, 0, 4]] and int(where.sum()) == 3 ** 4 + 9


@pytest.fixture(scope="module")
def lut_model(tiny_dataset, tmp_path_factory):
    """A small table trained on the tiny dataset through the command line, and its export."""
    d = tmp_path_factory.mktemp("lut")
    args = ["train", "--data", str(tiny_dataset), "--method", "lut", "--bins", "8", "--trees", "20", "--seed", "3"]
    assert main([*args, "--out", str(d / "lut.pt")]) == 0
    assert main(["export", "--model", str(d / "lut.pt"), "--out", str(d / "ex")]) == 0
    return d


def test_training_is_reproducible_to_the_byte(lut_model, tiny_dataset):
    """The same rows and seed give the same checkpoint bytes, at another torch thread count too."""
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1 if threads > 1 else 2)
        args = ["train", "--data", str(tiny_dataset), "--method", "lut", "--bins", "8", "--trees", "20", "--seed", "3"]
        assert main([*args, "--out", str(lut_model / "again.pt")]) == 0
    finally:
        torch.set_num_threads(threads)
    assert (lut_model / "again.pt").read_bytes() == (lut_model / "lut.pt").read_bytes()


def test_a_checkpoint_round_trips(lut_model, tmp_path):
    model, ck = registry.load(lut_model / "lut.pt")
    assert ck["kind"] == "lut" and isinstance(model, LookupModel)
    assert len(model.boosters) == ENSEMBLE and all(b.startswith("tree") for b in model.boosters)
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    registry.save(model, tmp_path / "a" / "lut.pt", ck["meta"])  # (torch names the archive after the file)
    again, ck2 = registry.load(tmp_path / "a" / "lut.pt")
    assert torch.equal(again.levels, model.levels) and int(again.threshold) == int(model.threshold)
    assert again.boosters == model.boosters and again.grid_json() == model.grid_json()
    registry.save(again, tmp_path / "b" / "lut.pt", ck2["meta"])
    assert (tmp_path / "b" / "lut.pt").read_bytes() == (tmp_path / "a" / "lut.pt").read_bytes()


def test_torch_the_graph_and_the_onboard_head_decide_alike(lut_model):
    """On a cube of every kind of pixel (skin-like, random, out of range, zero band pairs) under configurations
    in several slices: the torch reference, the graph run whole by onnxruntime and the numpy head (large frames,
    tiles on two workers) give the same mask and score, pixel for pixel."""
    import onnxruntime as ort

    from torchskin.onboard import OnboardDetector

    model, _ = registry.load(lut_model / "lut.pt")
    rng = np.random.default_rng(0)
    cube = (rng.random((3, 4, 96, 128)) * 0.8).astype(np.float32)
    cfg = np.array([[10.0, 5.0, 20.0, 0.1], [50.0, 40.0, 150.0, 0.45], [80.0, 85.0, 170.0, 0.95]], dtype=np.float32)
    centres = cell_centres(model.shift, model.lo, model.bins)
    for b, s in enumerate(model.slices(torch.from_numpy(cfg)).tolist()):  # the top half: cells near the region
        near = (model.levels[s] > 0).nonzero().squeeze(1)
        near = near[reflectance_of(centres[near], model.ref).amax(1) < 1.0]  # within detect's range
        assert near.numel(), f"slice {s} of the tiny model holds no cell above even odds"
        pick = near[torch.from_numpy(rng.integers(0, near.numel(), 48 * 128))]
        jitter = torch.from_numpy(rng.uniform(-0.5, 0.5, (48 * 128, 4))) * torch.exp2(model.shift.double())
        cube[b, :, :48] = reflectance_of(centres[pick] + jitter, model.ref).float().numpy().T.reshape(4, 48, 128)
    cube[0, :2, 50, :20] = 0.0  # NDGRI undefined
    cube[1, 2:, 51, :20] = 0.0  # NDSI undefined
    cube[2, :, 52, :10] = 3.0  # bright beyond the table's range
    with torch.no_grad():
        tm, ts = model.reference_detector()(torch.from_numpy(cube), torch.from_numpy(cfg))
    assert 0.05 < float(tm.float().mean()) < 0.95, "the cube must hold skin and non-skin pixels"
    graph = ort.InferenceSession(str(lut_model / "ex" / "detector.onnx"), providers=["CPUExecutionProvider"])
    gm, gs = graph.run(None, {"cube": cube, "config": cfg})
    det = OnboardDetector(lut_model / "ex" / "detector.onnx", threads=2, tile=4096)
    assert det.head_name == "lut"
    out = det(cube, cfg, min_reflectance=0)
    for mask, score in ((gm, gs), (out["mask"], out["score"])):
        assert np.array_equal(mask, tm.numpy()) and np.array_equal(score, ts.numpy())
    assert not out["mask"][0, 50, :20].any() and not out["mask"][1, 51, :20].any()
    # the decisions are the checkpoint's own
    R = torch.from_numpy(cube).permute(0, 2, 3, 1).reshape(-1, 4)
    X = torch.from_numpy(cfg).repeat_interleave(96 * 128, 0)
    assert np.array_equal(model.decide(R, X).reshape(3, 96, 128).numpy(), tm.numpy())


def test_graph_metadata_names_the_kind_its_head_and_its_bands(lut_model):
    import json

    import onnx

    from torchskin.bands import INDEX_BANDS, BandSet

    meta = {p.key: p.value for p in onnx.load(str(lut_model / "ex" / "detector.onnx")).metadata_props}
    assert meta["kind"] == "lut" and meta["onboard_head"] == "lut"
    assert BandSet.from_json(meta["bands"]) == INDEX_BANDS
    grid = json.loads(meta["lut_grid"])
    assert grid["bins"] == 8 and grid["n_bands"] == 4 and grid["config_counts"] == [6, 6, 2, 4]


def test_the_learner_sees_every_normalized_difference():
    R = np.array([[0.3, 0.1, 0.0, 0.0]])
    f = learner_features(R, np.array([[10.0, 20.0, 30.0]]))
    assert f.shape == (1, 4 + 6 + 1 + 3)
    np.testing.assert_allclose(f[0, 4:10], [0.5, 1.0, 1.0, 1.0, 1.0, 0.0])  # a + b = 0: 0
    assert math.isclose(f[0, 10], math.log(0.4)) and f[0, 11:].tolist() == [10.0, 20.0, 30.0]


def test_each_earthlib_spectrum_covers_every_stratum_of_configuration_and_brightness_once():
    C = torch.rand(7, 4, generator=torch.Generator().manual_seed(1)) * 0.5 + 0.1
    domain = torch.tensor([[0.0, 80.0], [0.0, 60.0], [0.0, 180.0]])
    draws = 20
    RC, XC, w = earthlib_negatives(C, domain, rows=7 * draws, nonskin=35, g=torch.Generator().manual_seed(3))
    assert RC.shape == (7 * draws, 4) and XC.shape == (7 * draws, 3) and w == 35 / (7 * draws)
    scale = (RC / C.repeat(draws, 1)).view(draws, 7, 4)
    assert torch.allclose(scale, scale[..., :1].expand_as(scale), rtol=1e-5)  # one factor on all bands of a draw
    a, b = EARTHLIB_SCALE
    u = torch.cat([((XC - domain[:, 0]) / (domain[:, 1] - domain[:, 0])).view(draws, 7, 3),
                   (torch.log(scale[..., :1].double()) - math.log(a)) / math.log(b / a)], -1)
    strata = torch.floor(u.double().clamp(1e-9, 1 - 1e-9) * draws)
    assert torch.equal(strata.sort(0).values, torch.arange(draws, dtype=strata.dtype)[:, None, None].expand_as(strata))
    again = earthlib_negatives(C, domain, rows=7 * draws, nonskin=35, g=torch.Generator().manual_seed(3))
    assert torch.equal(again[0], RC) and torch.equal(again[1], XC)


def test_shaded_earthlib_negatives_are_lit_by_the_sky_alone_under_the_training_suns():
    """With the training suns, each draw takes one sun (zenith and diffuse share together, each sun as often), and
    half of each spectrum's draws lie in shade: the spectrum times a sky view in SKY_VIEW times that sun's sky share
    per band. The other half keep one brightness factor on all bands."""
    C = torch.rand(7, 4, generator=torch.Generator().manual_seed(1)) * 0.5 + 0.1
    domain = torch.tensor([[0.0, 80.0], [0.0, 60.0], [0.0, 180.0], [0.0, 1.0]])
    sky = torch.tensor([[0.1, 0.08, 0.04, 0.02], [0.3, 0.25, 0.12, 0.07], [0.6, 0.5, 0.3, 0.2],
                        [0.8, 0.75, 0.5, 0.4], [0.95, 0.9, 0.8, 0.7]], dtype=torch.float64)
    skies = Skies(torch.tensor([10.0, 35.0, 55.0, 70.0, 85.0], dtype=torch.float64), sky[:, 0] + 0.001, sky, sky * 0.7)
    draws = 20
    RC, XC, _ = earthlib_negatives(C, domain, rows=7 * draws, nonskin=35, g=torch.Generator().manual_seed(3),
                                   skies=skies, features=(*FEATURES, DIFFUSE_SHARE))
    j = torch.searchsorted(skies.zenith_deg.float(), XC[:, 0].contiguous())
    assert torch.equal(skies.zenith_deg.float()[j], XC[:, 0])  # a training sun's zenith
    assert torch.equal(skies.diffuse_share.float()[j], XC[:, 3])  # with that sun's diffuse share
    assert torch.equal(torch.bincount(j.view(draws, 7)[:, 0], minlength=5), torch.full((5,), draws // 5))
    base = C.repeat(draws, 1).double()
    shaded = RC.double() / (base * sky[j])
    flat = RC.double() / base
    in_shade = torch.isclose(shaded, shaded[:, :1], rtol=1e-5).all(1) & ~torch.isclose(flat, flat[:, :1], rtol=1e-5).all(1)
    assert torch.equal(in_shade.view(draws, 7).sum(0), torch.full((7,), round(draws * SHADE_SHARE)))
    lo, hi = SKY_VIEW
    assert bool(((shaded[in_shade, 0] >= lo - 1e-6) & (shaded[in_shade, 0] <= hi + 1e-6)).all())
    a, b = EARTHLIB_SCALE
    assert torch.isclose(flat[~in_shade], flat[~in_shade, :1], rtol=1e-5).all()
    assert bool(((flat[~in_shade, 0] >= a - 1e-6) & (flat[~in_shade, 0] <= b + 1e-6)).all())
    # shade tilts every spectrum towards the blue, as its sun's sky does
    assert torch.allclose(RC[in_shade, 3] / RC[in_shade, 0], (C.repeat(draws, 1)[in_shade, 3] / C.repeat(draws, 1)[
        in_shade, 0]) * (sky[j[in_shade], 3] / sky[j[in_shade], 0]).float(), rtol=1e-5)


def test_without_a_sun_zenith_column_the_training_sun_is_drawn_on_its_own():
    """A table without the sun zenith still takes each draw's sun (and its diffuse share) from the training suns,
    each as often, on a stratum of its own rather than the first column's; sky shares of other bands are refused."""
    C = torch.rand(7, 4, generator=torch.Generator().manual_seed(1)) * 0.5 + 0.1
    domain = torch.tensor([[0.0, 90.0], [0.0, 180.0], [0.0, 1.0]])
    sky = torch.linspace(0.9, 0.1, 20, dtype=torch.float64).view(5, 4)
    skies = Skies(torch.arange(5.0, dtype=torch.float64), torch.arange(5.0, dtype=torch.float64) / 10, sky, sky / 2)
    feats = ("camera_zenith_deg", "relative_azimuth_deg", DIFFUSE_SHARE)
    _, XC, _ = earthlib_negatives(C, domain, rows=7 * 20, nonskin=35, g=torch.Generator().manual_seed(3),
                                  skies=skies, features=feats)
    sun = torch.round(XC[:, 2] * 10).long()
    assert torch.equal(torch.bincount(sun.view(20, 7)[:, 0], minlength=5), torch.full((5,), 4))
    assert bool((sun != torch.floor(XC[:, 0] / 90.0 * 5).long()).any())  # not the camera zenith's stratum
    with pytest.raises(ValueError, match="sky shares hold 3 bands"):
        earthlib_negatives(C, domain, rows=140, nonskin=35, g=torch.Generator().manual_seed(3),
                           skies=Skies(skies.zenith_deg, skies.diffuse_share, sky[:, :3], sky[:, :3]), features=feats)


def test_the_training_skies_are_the_datasets_suns_and_blue(tiny_dataset):
    """SPECTRL2 for the dataset's suns, recomputed from their zenith and atmosphere, gives the sky share at 544 nm
    that the renderer recorded (the diffuse share); it falls with wavelength under every sun. The isotropic sky's
    share (what a cast shadow receives) is smaller and bluer."""
    from torchskin.dataset.files import dataset_bands

    skies = training_skies(tiny_dataset, "line", dataset_bands(tiny_dataset))
    assert skies is not None and 2 <= len(skies.zenith_deg) <= 12 * 3 and bool((skies.zenith_deg.diff() >= 0).all())
    assert torch.allclose(skies.sky[:, 0], skies.diffuse_share, atol=1e-6)
    assert bool((skies.sky.diff(dim=1) < 0).all())
    # a cast shadow hides the sky around the sun too: it gets less of the panels' light, and bluer
    assert bool(((skies.shadow > 0) & (skies.shadow < skies.sky)).all())
    assert bool(((skies.shadow[:, -1] / skies.shadow[:, 0]) < (skies.sky[:, -1] / skies.sky[:, 0])).all())


def test_learning_needs_both_classes():
    R = torch.rand(50, 4) + 0.1
    with pytest.raises(ValueError, match="at least 10 skin and 10 non-skin"):
        learn(torch.zeros(50, 3), R, torch.ones(50, dtype=torch.bool), trees=2, bins=4)


def test_without_the_configuration_one_table_serves_every_sun_and_camera(tiny_dataset, tmp_path):
    out = tmp_path / "flat.pt"
    assert main(["train", "--data", str(tiny_dataset), "--method", "lut", "--bins", "8", "--trees", "20",
                 "--no-configuration", "--out", str(out)]) == 0
    model, ck = registry.load(out)
    assert model.levels.shape[0] == 1 and not model.config_inputs
    assert ck["meta"]["options"]["configuration"] is False  # the training summary says so
    R = torch.rand(300, 4, generator=torch.Generator().manual_seed(0)) * 0.6
    X1, X2 = torch.tensor([[5.0, 5.0, 10.0, 0.1]]).expand(300, 4), torch.tensor([[85.0, 80.0, 170.0, 0.9]]).expand(300, 4)
    assert torch.equal(model.decide(R, X1), model.decide(R, X2))


def test_the_region_figure_is_drawn(lut_model, tiny_dataset, tmp_path):
    from torchskin.detectors.lut import LookupKind

    LookupKind.region_figure(lut_model / "lut.pt", tiny_dataset, tmp_path / "region.png")
    assert (tmp_path / "region.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(ValueError, match="not a lut checkpoint"):
        from torchskin.detectors.boxes import BoxModel

        registry.save(BoxModel(), tmp_path / "box.pt")
        LookupKind.region_figure(tmp_path / "box.pt", tiny_dataset, tmp_path / "box.png")
    assert not (tmp_path / "box.png").exists()


@pytest.mark.parametrize("flag, value, words", [("--bins", "1", "--bins must lie in [2, 45]"),
                                                ("--bins", "46", "--bins must lie in [2, 45]"),
                                                ("--trees", "0", "--trees must be at least 1"),
                                                ("--support-dilation", "-1", "--support-dilation must be 0 or more"),
                                                ("--earthlib-margin", "-2", "--earthlib-margin must be -1 (none)"),
                                                ("--earthlib-margin", "1000000000", "at most --bins (32)"),
                                                ("--support-dilation", "33", "at most --bins (32)"),
                                                ("--max-rows", "10", "--max-rows must be at least 100")])
def test_table_settings_out_of_range_are_refused_in_one_line(tiny_dataset, tmp_path, capsys, flag, value, words):
    out = tmp_path / "lut.pt"
    assert main(["train", "--data", str(tiny_dataset), "--method", "lut", flag, value, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and words in err, err
    assert not out.exists()


def test_a_damaged_table_is_one_line_naming_the_file(lut_model, tiny_dataset, tmp_path, capsys):
    ck = torch.load(lut_model / "lut.pt", weights_only=True)
    ck["levels_xz"] = ck["levels_xz"][:100]  # truncated
    torch.save(ck, tmp_path / "broken.pt")
    assert main(["evaluate", "--data", str(tiny_dataset), "--model", str(tmp_path / "broken.pt")]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "broken.pt" in err and "damaged" in err, err


@pytest.mark.parametrize("n,bins,ref", [(2, 40, 0), (3, 16, 2), (4, 8, 0), (4, 8, 2), (5, 6, 3), (7, 4, 6)])
def test_the_onboard_head_puts_every_pixel_in_the_torch_cell_for_any_band_count(n, bins, ref):
    """The numpy head (its ratio chains on either side of the reference band, one shift and one clip over every
    axis, its offset table) gives the cell torch gives, for any band count and reference, on pixels inside, outside
    and at the edges of the table, with a band at 0, and when the offsets sum below 0 (subtracted in a pass)."""
    from torchskin.bands import LUT_COORDINATES
    from torchskin.onboard.lut import LutHead

    rng = np.random.default_rng(n)
    m = LookupModel(n, bins, bands=BandSet.of(list(range(500, 500 + 50 * n, 50))), config_counts=(1, 1, 1))
    shift = [int(v) for v in rng.integers(19, 23, n)]
    lo = [(127 - 5) * 2 ** (23 - shift[0])] + [int(v) for v in rng.integers(-bins, 0, n - 1)]
    # the second: the brightness from the smallest normal float, a ratio axis from far below 0: offsets below 0
    for sh, first in ((shift, lo), ([22, 19, *shift[2:]], [2, -2 * bins, *lo[2:]])):
        m.set_range(ref, sh, first)
        grid = json.loads(m.grid_json())
        assert grid["coordinates"] == LUT_COORDINATES
        head = LutHead(grid, np.zeros(-(-bins ** n // 8), dtype=np.uint8))
        base = sum(bins ** (n - 1 - k) * f for k, f in enumerate(first))
        assert head.offset_free == (base >= 0) and head.base == max(base, 0)
        assert head.table(0).shape == (head.base + bins ** n,)
        R = (rng.random((n, 5000)) ** 2 * rng.choice([0.01, 0.5, 3.0], (1, 5000))).astype(np.float32)
        R[:, :50] = 0.0
        R[: n // 2, 50:100] = 0.0
        sc = head.scratch(R.shape[1])
        head._cells(R, sc)
        want = m.cells_of(torch.from_numpy(R.T)).numpy()
        assert np.array_equal(sc["cell"] - head.base, want)
        assert len(np.unique(want)) > 20  # pixels all over the table, not one edge cell


def test_the_earthlib_margin_is_the_cells_of_the_spectra_and_their_axis_neighbours():
    """``earthlib_cells``: margin 0 holds exactly the cells of the spectra at the margin's brightness factors;
    each step adds the neighbours along one axis at a time (2n per cell), nothing else."""
    from torchskin.detectors.lut.train import MARGIN_SCALES, earthlib_cells

    m = LookupModel(4, 8, config_counts=(1, 1, 1))
    m.set_range(3, [23, 22, 22, 22], [127 - 6, -4, -4, -4])
    spectra = torch.tensor([[0.3, 0.2, 0.5, 0.1], [0.05, 0.06, 0.3, 0.2]])
    a, b, k = MARGIN_SCALES
    scales = torch.logspace(math.log10(a), math.log10(b), k)
    own = torch.zeros(8 ** 4, dtype=torch.bool)
    own[m.cells_of((spectra[:, None, :] * scales[None, :, None]).reshape(-1, 4))] = True
    assert torch.equal(earthlib_cells(m, spectra, 0), own)
    grown = own.reshape(8, 8, 8, 8).clone()
    for q in own.reshape(8, 8, 8, 8).nonzero().tolist():
        for axis in range(4):
            for step in (-1, 1):
                p = list(q)
                p[axis] += step
                if 0 <= p[axis] < 8:
                    grown[tuple(p)] = True
    assert torch.equal(earthlib_cells(m, spectra, 1), grown.reshape(-1))


def test_no_earthlib_train_spectrum_is_skin_at_any_brightness(lut_model):
    """The trained table (default margin 0: the cells themselves) holds level 0, in every slice, wherever an earthlib train spectrum
    falls at any of the margin's brightness factors."""
    from torchskin.detectors.features import earthlib_reflectance
    from torchskin.detectors.lut.train import earthlib_cells

    model, ck = registry.load(lut_model / "lut.pt")
    near = earthlib_cells(model, earthlib_reflectance("train"), 0)
    assert near.any() and not model.levels[:, near].any()
    assert ck["meta"]["options"]["earthlib_margin"] == 0 and ck["meta"]["earthlib_margin_cells"] >= 0


def test_a_lut_detector_trains_exports_and_runs_onboard_on_a_five_band_camera(tmp_path, capsys, lut_model,
                                                                             tiny_dataset):
    """A silicon five-band camera (MicaSense RedEdge-MX's centres and widths): the table is learned over its
    bands, the checkpoint and the graph's metadata name them, the card says five, and the torch reference, the
    graph run whole and the numpy head tiled on two workers agree pixel for pixel (5^5 cells a slice: the table's
    slices do not start on a byte). `evaluate` judges it in its own bands, without the static box."""
    import onnx
    import onnxruntime as ort
    from conftest import tiny_generate

    from torchskin.bands import BandSet
    from torchskin.onboard import OnboardDetector

    bands = BandSet.parse("475/32,560/27,668/14,717/12,842/57")
    tiny_generate(tmp_path, "475/32,560/27,668/14,717/12,842/57")
    args = ["train", "--data", str(tmp_path / "ds"), "--method", "lut", "--bins", "5", "--trees", "20", "--seed", "3"]
    assert main([*args, "--out", str(tmp_path / "lut5.pt")]) == 0
    assert main(["export", "--model", str(tmp_path / "lut5.pt"), "--out", str(tmp_path / "ex")]) == 0
    model, ck = registry.load(tmp_path / "lut5.pt")
    assert model.n_bands == 5 and model.bands == bands and BandSet.from_json(ck["bands"]) == bands
    meta = {p.key: p.value for p in onnx.load(str(tmp_path / "ex" / "detector.onnx")).metadata_props}
    assert BandSet.from_json(meta["bands"]) == bands
    card = (tmp_path / "ex" / "detector.md").read_text()
    assert "(B, 5, H, W): ELM-calibrated reflectance at 475, 560, 668, 717, 842 nm" in card and "five band" in card
    rng = np.random.default_rng(1)
    cube = (rng.random((2, 5, 48, 64)) * 0.7).astype(np.float32)
    cfg_rows = np.array([[20.0, 10.0, 30.0], [60.0, 70.0, 160.0]], dtype=np.float32)  # no 544 nm band: no share
    with torch.no_grad():
        tm, ts = model.reference_detector()(torch.from_numpy(cube), torch.from_numpy(cfg_rows))
    gm, gs = ort.InferenceSession(str(tmp_path / "ex" / "detector.onnx"),
                                  providers=["CPUExecutionProvider"]).run(None, {"cube": cube, "config": cfg_rows})
    det = OnboardDetector(tmp_path / "ex" / "detector.onnx", threads=2, tile=1024)
    assert det.head_name == "lut" and det.n_bands == 5
    out = det(cube, cfg_rows, min_reflectance=0)
    assert 0 < int(tm.sum()) < tm.numel(), "the cube must hold pixels on both sides"
    for mask, score in ((gm, gs), (out["mask"], out["score"])):
        assert np.array_equal(mask, tm.numpy()) and np.array_equal(score, ts.numpy())
    # evaluate in the model's own bands: no static box (it reads the index bands), the checkpoint and its graph alike
    from torchskin.dataset.files import read_rows
    from torchskin.evaluation import MIN_REFLECTANCE, evaluate

    res = evaluate(tmp_path / "ds", [str(tmp_path / "lut5.pt"), str(tmp_path / "ex" / "detector.onnx")])
    assert res["static"] is None and len(res["models"]) == 2 and res["bands_nm"] == list(bands.centers)
    a, b = (dict(m["overall"]) for m in res["models"])
    assert math.isnan(a.pop("area_mean")) and math.isnan(b.pop("area_mean")) and a == b  # no (NDGRI, NDSI) plane
    from torchskin.detectors.features import feature_columns, stack_features

    rows = read_rows(tmp_path / "ds", [*feature_columns(model.features), *bands.columns, "label", "shadow"])
    R = torch.from_numpy(rows.stack(bands.columns, np.float32))
    X = torch.from_numpy(stack_features(rows, model.features))
    hit = model.decide(R, X).bool() & (R.mean(-1) > MIN_REFLECTANCE)
    lit = torch.from_numpy(rows["label"] & ~rows["shadow"])
    assert res["learned"]["pd_sunlit"] == pytest.approx(float(hit[lit].float().mean()), abs=1e-12)
    assert res["learned"]["sunlit_skin_pixels"] == int(lit.sum()) > 0
    capsys.readouterr()
    five = ["--model", str(tmp_path / "lut5.pt")]
    assert main(["evaluate", "--data", str(tmp_path / "ds"), *five, "--plots", str(tmp_path / "plots")]) == 0
    table = capsys.readouterr().out
    assert "lut5.pt" in table and "static box" not in table and (tmp_path / "plots" / "pd_heatmap.png").is_file()
    for data, models, words in ((tmp_path / "ds", [*five, "--model", str(lut_model / "lut.pt")], "different bands"),
                                (tiny_dataset, five, "lacks the 475, 560, 668, 717, 842 nm bands")):
        assert main(["evaluate", "--data", str(data), *models]) == 2
        err = capsys.readouterr().err.strip()
        assert "\n" not in err and words in err, err


def test_a_camera_with_its_filters_off_is_judged_positionally(lut_model, tiny_dataset, tmp_path):
    """The filter-tolerance rows: a dataset rendered 5 nm above the index bands lacks the model's bands, unless
    read in order as the model's own (``positional_bands``): then its decisions are the model's on those columns,
    and the static box is judged on them too. A table that takes the diffuse share is refused there: the dataset
    records no sky_fraction off 544 nm."""
    from conftest import tiny_generate

    from torchskin.dataset.files import read_rows
    from torchskin.evaluation import MIN_REFLECTANCE, evaluate

    ds = tiny_generate(tmp_path, "549,638,1085,1585")
    with pytest.raises(ValueError, match="does not record diffuse_share"):  # sky_fraction is recorded at 544 nm
        evaluate(ds, [str(lut_model / "lut.pt")], positional_bands=True)
    model_path = str(tmp_path / "angles.pt")  # the sun-and-camera table
    assert main(["train", "--data", str(tiny_dataset), "--method", "lut",
                 "--bins", "8", "--trees", "20", "--seed", "3", "--no-diffuse-share", "--out", model_path]) == 0
    with pytest.raises(ValueError, match="lacks the 544, 633, 1080, 1580 nm bands"):
        evaluate(ds, [model_path])
    res = evaluate(ds, [model_path], positional_bands=True)
    assert res["dataset_bands_nm"] == [549.0, 638.0, 1085.0, 1585.0] and res["static"] is not None
    model, _ = registry.load(model_path)
    from torchskin.detectors.features import feature_columns, stack_features

    rows = read_rows(ds, [*feature_columns(model.features), "r549", "r638", "r1085", "r1585", "label", "shadow"])
    R = torch.from_numpy(rows.stack(["r549", "r638", "r1085", "r1585"], np.float32))
    hit = model.decide(R, torch.from_numpy(stack_features(rows, model.features))).bool() & (R.mean(-1) > MIN_REFLECTANCE)
    lit = torch.from_numpy(rows["label"] & ~rows["shadow"])
    assert res["learned"]["pd_sunlit"] == pytest.approx(float(hit[lit].float().mean()), abs=1e-12)
    (tmp_path / "five").mkdir()
    five = tiny_generate(tmp_path / "five", "rededge-mx")
    with pytest.raises(ValueError, match="holds 5 bands; the models read 4"):
        evaluate(five, [model_path], positional_bands=True)
