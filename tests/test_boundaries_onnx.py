"""Learned boundaries: quantile training, checkpoints, ONNX export and the torch-free onboard runtime."""

import json
import math
import subprocess
import sys

import numpy as np
import pytest
import torch

from torchskin.detectors import boxes as Bx
from torchskin.detectors.boxes import BoxDetector
from torchskin.detectors.features import FEATURES, ratio_indices, tuning_configs
from torchskin.export import export

pytestmark = pytest.mark.slow  # most tests train boundaries or share the module fixture that does


def synthetic(n=4000, seed=0):
    g = torch.Generator().manual_seed(seed)
    X = torch.stack([torch.rand(n, generator=g) * 89, torch.rand(n, generator=g) * 70,
                     torch.rand(n, generator=g) * 180], -1)
    ndgri = -0.45 + 0.004 * X[:, 0] + 0.05 * torch.randn(n, generator=g)  # drifts with sun zenith
    ndsi = 0.72 - 0.003 * X[:, 1] + 0.03 * torch.randn(n, generator=g)
    return X, torch.stack([ndgri, ndsi], -1)


@pytest.fixture(scope="module")
def trained():
    X, Y = synthetic()
    return X, Y, Bx.train_quantiles(X, Y, q=0.05, steps=1500)


def test_learned_boxes_are_accurate_conditional_quantiles(trained):
    X, Y, res = trained
    Xt, Yt = synthetic(20000, seed=1)
    with torch.no_grad():
        box = res.model(Xt)
    assert bool((box[:, 1] >= box[:, 0]).all() and (box[:, 3] >= box[:, 2]).all())
    below = (Yt[:, 0] < box[:, 0]).float().mean()
    above = (Yt[:, 0] > box[:, 1]).float().mean()
    assert abs(float(below) - 0.05) < 0.015 and abs(float(above) - 0.05) < 0.015
    # the box follows the configuration: high sun zenith moves the NDGRI limits up as the data do
    lo = res.model(torch.tensor([[10.0, 30.0, 90.0]]))[0]
    hi = res.model(torch.tensor([[80.0, 30.0, 90.0]]))[0]
    assert float((hi[0] - lo[0]).detach()) == pytest.approx(0.004 * 70, abs=0.06)


def test_checkpoint_round_trip(trained, tmp_path):
    X, _, res = trained
    Bx.save(res.model, tmp_path / "m.pt", {"note": "test"})
    Bx.save(res.model, tmp_path / "m2.pt", {"note": "test"})
    assert (tmp_path / "m.pt").read_bytes() == (tmp_path / "m2.pt").read_bytes()  # reproducible bytes
    back = Bx.load(tmp_path / "m.pt")
    torch.testing.assert_close(back(X[:50]), res.model(X[:50]))


def test_onnx_matches_torch_and_runs_without_torch(trained, tmp_path):
    import onnx

    X, _, res = trained
    paths = export(res.model, tmp_path, manifest_sha256="abc123")
    m = onnx.load(paths["detector"])
    meta = {p.key: p.value for p in m.metadata_props}
    assert m.opset_import[0].version >= 17 and json.loads(meta["features"]) == list(FEATURES)
    assert meta["training_manifest_sha256"] == "abc123" and json.loads(meta["bands_nm"]) == [544.0, 633.0, 1080.0, 1580.0]
    g = torch.Generator().manual_seed(3)
    cube = (torch.rand(3, 4, 17, 23, generator=g) * 0.6 + 0.02).float()
    cfg = X[:3].float()
    with torch.no_grad():
        mask_t, score_t = BoxDetector(res.model)(cube, cfg)
        boxes_t = res.model(X[:200])
    np.save(tmp_path / "cube.npy", cube.numpy())
    np.save(tmp_path / "cfg.npy", cfg.numpy())
    np.save(tmp_path / "x.npy", X[:200].numpy())
    script = f"""
import sys, json
sys.modules["torch"] = None  # importing torch must fail here
import numpy as np
from torchskin.onboard import OnboardBoxes, OnboardDetector
d = OnboardDetector({paths['detector']!r}); b = OnboardBoxes({paths['boundaries']!r})
out = d(np.load({str(tmp_path / 'cube.npy')!r}), np.load({str(tmp_path / 'cfg.npy')!r}))
np.save({str(tmp_path / 'mask.npy')!r}, out["mask"]); np.save({str(tmp_path / 'score.npy')!r}, out["score"])
np.save({str(tmp_path / 'boxes.npy')!r}, b(np.load({str(tmp_path / 'x.npy')!r}))["boxes"])
print(json.dumps({{"torch_loaded": "torch" in sys.modules and sys.modules["torch"] is not None}}))
"""
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout.strip().splitlines()[-1]) == {"torch_loaded": False}
    boxes = np.load(tmp_path / "boxes.npy")
    assert np.abs(boxes - boxes_t.numpy()).max() < 1e-5
    mask, score = np.load(tmp_path / "mask.npy"), np.load(tmp_path / "score.npy")
    assert np.abs(score - score_t.numpy()).max() < 1e-5
    differ = mask != mask_t.numpy()
    assert (np.abs(score_t.numpy()[differ]) < 1e-6).all()  # only pixels on a boundary may differ
    assert mask.any() and not mask.all()


def test_onboard_rejects_bad_input_and_flags_out_of_domain(trained, tmp_path):
    from torchskin.onboard import OnboardDetector

    _, _, res = trained
    paths = export(res.model, tmp_path)
    d = OnboardDetector(paths["detector"])
    good = np.full((1, 4, 4, 4), 0.3, dtype=np.float32)
    cfg = np.array([[30.0, 20.0, 90.0]])
    out = d(good, cfg)
    assert out["mask"].shape == (1, 4, 4) and not out["out_of_domain"].any()
    assert d(good, np.array([[95.0, 20.0, 90.0]]))["out_of_domain"].tolist() == [True]
    assert np.array_equal(d(good.astype(np.float64), cfg)["score"], out["score"])  # float64 converted, not refused
    for bad, msg in [(good[0], "rank 4"), (good[:, :3], "4 bands"),
                     (np.where(np.arange(4) == 0, np.nan, good).astype(np.float32), "NaN"),
                     (-0.1 * good, "negative"), (-good, "far below 0")]:
        with pytest.raises(ValueError, match=msg):
            d(bad, cfg)
    with pytest.raises(ValueError, match="config must be"):
        d(good, np.array([[30.0, 20.0]]))
    with pytest.raises(ValueError, match="cannot load ONNX model"):
        OnboardDetector(tmp_path / "missing.onnx")


def test_train_export_detect_pipeline_on_a_generated_dataset(tmp_path, capsys):
    from torchskin.cli import main
    from torchskin.dataset.config import resolve_config
    from torchskin.dataset.generate import generate
    from torchskin.render.meshes import sphere_mesh, write_obj

    v, f = sphere_mesh(0.35, 3)
    obj = tmp_path / "head.obj"
    write_obj(obj, v + [0.0, 0.0, 0.9], f)
    cfg = resolve_config({"camera": {"width": 48, "height": 48, "range_m": [5.0, 20.0]}, "sun": {"per_pose": 4},
                          "skin": {"per_pose": 2}, "subject": {"meshes": [str(obj)]}, "confusers": {"count": [0, 0]},
                          "sampling": {"groups_per_shard": 2, "pixels_per_class": 32}})
    generate(cfg, 64, 0, tmp_path / "data", quiet=True)
    assert main(["train", "--data", str(tmp_path / "data"), "--out", str(tmp_path / "m.pt"), "--steps", "300",
                 "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["rows"] > 100
    # the training domain is the dataset's declared ranges, not the extremes of its few draws
    assert Bx.load(tmp_path / "m.pt").domain.tolist() == [[0.0, 89.0], [0.0, 90.0], [0.0, 180.0]]
    # calibration to the budgets on a validation set: one scale, never looser than training's; the record kept
    from torchskin.evaluation import calibrate_to_budget, evaluate

    loose = calibrate_to_budget(tmp_path / "m.pt", tmp_path / "data", tmp_path / "loose.pt", scene_budget=0.5)
    assert loose["after"] == loose["before"] == float(Bx.load(tmp_path / "m.pt").scale)
    tight = calibrate_to_budget(tmp_path / "m.pt", tmp_path / "data", tmp_path / "tight.pt", scene_budget=0.0)
    assert tight["knob"] == "scale" and tight["after"] <= tight["before"] and tight["pfa_scene"] == 0.0
    assert float(Bx.load(tmp_path / "tight.pt").scale) == tight["after"]
    assert torch.load(tmp_path / "tight.pt", weights_only=True)["meta"]["calibration"] == tight
    judged = evaluate(tmp_path / "data", [tmp_path / "tight.pt"])["models"][0]["overall"]
    assert judged["pfa_scene"] == 0.0 and judged["pfa"] <= 1e-3
    assert main(["export", "--model", str(tmp_path / "m.pt"), "--out", str(tmp_path / "exports"), "--json"]) == 0
    paths = json.loads(capsys.readouterr().out)
    import onnx

    meta = {p.key: p.value for p in onnx.load(paths["detector"]).metadata_props}
    assert len(meta["training_manifest_sha256"]) == 64  # the dataset's manifest hash travels with the model
    cube = np.full((4, 8, 8), 0.3, dtype=np.float32)
    cube[0], cube[1], cube[2], cube[3] = 0.3, 0.6, 0.55, 0.08  # a skin-like spectrum
    np.save(tmp_path / "cube.npy", cube)
    args = ["detect", "--model", paths["detector"], "--cube", str(tmp_path / "cube.npy"), "--sun-zenith", "40",
            "--camera-zenith", "30", "--relative-azimuth", "60", "--out", str(tmp_path / "mask.png"), "--json"]
    script = ("import sys; sys.modules['torch'] = None; from torchskin.cli import main; "
              f"sys.exit(main({args!r}))")
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["shape"] == [1, 8, 8] and out["out_of_domain"] == [False]
    assert (tmp_path / "mask.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    bad = subprocess.run([sys.executable, "-c", script.replace("'40'", "'40'").replace("'--camera-zenith', '30', ", "")],
                         capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "--camera-zenith" in bad.stderr
    cube[:, 0, :3] = -1e-4  # 3 dark pixels with noise below 0 in every band: refused, unless --clip-negative
    np.save(tmp_path / "cube.npy", cube)
    assert main(args) == 2 and "--clip-negative" in capsys.readouterr().err
    assert main(args + ["--clip-negative"]) == 0
    clipped = json.loads(capsys.readouterr().out)
    assert clipped["clipped_values"] == [12] and clipped["skin_pixels"] == out["skin_pixels"] - 3  # 3 black pixels


def test_false_alarm_tuning_and_evaluation(tmp_path, trained, capsys):
    X, Y, res = trained
    model = res.model
    pts = torch.tensor([[-0.30, 0.70], [-0.25, 0.72], [0.4, 0.1]])  # two confusers inside typical boxes
    before = float(Bx.false_alarm_rate(model(X[:200]).detach(), pts).max())
    scale = Bx.tune_false_alarms(model, X[:200], pts, budget=0.0)
    after = float(Bx.false_alarm_rate(model(X[:200]).detach(), pts).max())
    assert before > 0 and after == 0.0 and 0.0 <= scale < 1.0
    model.scale.fill_(1.0)
    # evaluation against the static box on a tiny hand-made dataset folder
    import pyarrow as pa
    import pyarrow.parquet as pq

    from torchskin.detect import DEFAULT_BOX
    from torchskin.evaluation import evaluate

    n = 400
    g = torch.Generator().manual_seed(5)
    cfg = X[:n]
    ndgri = torch.rand(n, generator=g) * 0.8 - 0.7
    ndsi = torch.rand(n, generator=g) * 0.6 + 0.3
    label = torch.arange(n) % 2 == 0
    shadow = torch.arange(n) % 4 == 0
    d = tmp_path / "ds"
    d.mkdir()
    refl = {"r544": 0.4 * (1 + ndgri), "r633": 0.4 * (1 - ndgri), "r1080": 0.3 * (1 + ndsi), "r1580": 0.3 * (1 - ndsi)}
    glint = torch.arange(n) % 8 == 2  # sunlit skin rows seen in the mirror direction (θr = θi, Δφ = 180°)
    pq.write_table(pa.table({"sun_zenith_deg": cfg[:, 0].numpy(), "camera_zenith_deg": cfg[:, 1].numpy(),
                             "relative_azimuth_deg": cfg[:, 2].numpy(), "label": label.numpy(),
                             "shadow": shadow.numpy(), "ndgri": ndgri.numpy(), "ndsi": ndsi.numpy(),
                             "group": torch.arange(n).numpy(), "sun": (torch.arange(n) * 0).numpy(),
                             "skin": (torch.arange(n) * 0).numpy(), **{k: v.numpy() for k, v in refl.items()},
                             "theta_i_deg": torch.full((n,), 60.0).numpy(),
                             "theta_r_deg": torch.where(glint, 60.0, 0.0).numpy(),
                             "delta_phi_deg": torch.where(glint, 180.0, 0.0).numpy()}), d / "shard-00000.parquet")
    Bx.save(model, tmp_path / "m.pt")
    r = evaluate(d, tmp_path / "m.pt")
    inside = ((ndgri >= DEFAULT_BOX.b1) & (ndgri <= DEFAULT_BOX.b2) & (ndsi >= DEFAULT_BOX.c1) & (ndsi <= DEFAULT_BOX.c2))
    assert r["static"]["pd"] == pytest.approx(float(inside[label].float().mean()))
    assert r["static"]["pfa_scene"] == pytest.approx(float(inside[~label].float().mean()))
    assert 0.0 <= r["learned"]["pd"] <= 1.0 and r["bins"] and len(r["roc"]["learned"]) == len(r["roc"]["scales"])
    from torchskin.cli import main

    assert main(["evaluate", "--data", str(d), "--model", str(tmp_path / "m.pt"), "--plots", str(tmp_path / "p"),
                 "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert set(doc) >= {"learned", "static", "bins"} and (tmp_path / "p" / "roc.png").exists()
    assert (tmp_path / "p" / "boxes.png").stat().st_size > 1000
    lit = label & ~shadow  # each row is its own configuration here: the per-configuration mean is pooled Pd
    assert r["static"]["pd_sunlit_mean_over_configs"] == pytest.approx(float(inside[lit].float().mean()))
    # the exported boundaries.onnx evaluates to the same figures as the checkpoint
    from torchskin.export import export

    paths = export(model, tmp_path / "exports")
    r_onnx = evaluate(d, paths["boundaries"])
    assert r_onnx["learned"]["pd"] == pytest.approx(r["learned"]["pd"], abs=1e-6)
    assert r_onnx["learned"]["pfa"] == pytest.approx(r["learned"]["pfa"], abs=1e-6)
    # several models in one table: the checkpoint, both exports and the static box, one JSON entry each
    r3 = evaluate(d, [tmp_path / "m.pt", paths["boundaries"], paths["detector"]])
    names = [m["name"] for m in r3["models"]]
    assert names == ["m.pt", "boundaries.onnx", "detector.onnx", "static box (thesis)"]
    ck, onnx_b, det, stat = (m["overall"] for m in r3["models"])
    assert stat["pd"] == pytest.approx(r["static"]["pd"]) and stat["area_mean"] == pytest.approx(
        (DEFAULT_BOX.b2 - DEFAULT_BOX.b1) * (DEFAULT_BOX.c2 - DEFAULT_BOX.c1))
    for k in ("pd", "pd_sunlit", "pd_shadow", "pfa_scene", "pfa"):  # detector.onnx on B x 4 x 1 x 1 pixels
        assert det[k] == pytest.approx(ck[k], abs=3e-3), k
    assert det["area_mean"] == pytest.approx(ck["area_mean"], rel=0.1)  # the grid measure of the same boxes
    assert ck["glint_pixels"] == int((glint & label & ~shadow).sum()) > 0
    assert main(["evaluate", "--data", str(d), "--model", str(tmp_path / "m.pt"), "--model", paths["detector"]]) == 0
    text = capsys.readouterr().out
    assert "detector.onnx" in text and "static box (thesis)" in text


def diagonal(n=6000, seed=0):
    """Skin whose (NDGRI, NDSI) walks along a diagonal with sun zenith, and confusers off the diagonal where a
    single box spanning the whole walk would have to include them."""
    g = torch.Generator().manual_seed(seed)
    X = torch.stack([torch.rand(n, generator=g) * 80, torch.rand(n, generator=g) * 70,
                     torch.rand(n, generator=g) * 180], -1)
    t = X[:, 0] / 80
    Y = torch.stack([-0.6 + 0.5 * t, 0.55 + 0.3 * t], -1) + 0.015 * torch.randn(n, 2, generator=g)
    C = torch.tensor([[-0.5, 0.8], [-0.45, 0.84], [-0.2, 0.58], [-0.15, 0.6], [0.3, 0.1], [-0.8, 0.2]])
    return X, Y, C


def test_coverage_boxes_follow_the_configuration_and_keep_confusers_out():
    X, Y, C = diagonal()
    res = Bx.train_boxes(X, Y, C, steps=800, margin=0.02)
    flat = Bx.train_boxes(X, Y, C, hidden=0, steps=800, margin=0.02)
    Xt, Yt, _ = diagonal(20000, seed=1)
    with torch.no_grad():
        pd = float(Bx.soft_inside(res.model(Xt), Yt, 1e-9).mean())
        pd_flat = float(Bx.soft_inside(flat.model(Xt), Yt, 1e-9).mean())
        grid = tuning_configs(res.model, X, grid=12)
        boxes = res.model(grid)
    # no confuser within the margin of any box over the whole training domain (no tuning needed)
    assert float(Bx.margin_violation(boxes, C, 0.0).max()) == 0.0
    assert Bx.tune_false_alarms(res.model, grid, C, budget=0.0) == 1.0
    # the configuration-dependent box covers the walk; one constant box cannot without a confuser inside
    assert pd > 0.95 and pd_flat < 0.8, (pd, pd_flat)
    assert bool((boxes[:, 1] > boxes[:, 0]).all() and (boxes[:, 3] > boxes[:, 2]).all())
    lo, hi = res.model(torch.tensor([[5.0, 30.0, 90.0], [75.0, 30.0, 90.0]])).detach()
    assert float(hi[0] - lo[0]) == pytest.approx(0.5 * 70 / 80, abs=0.1)  # NDGRI edges move with the sun
    assert list(res.model.domain[0]) == pytest.approx([float(X[:, 0].min()), float(X[:, 0].max())])
    with pytest.raises(ValueError, match="margin"):
        Bx.train_boxes(X, Y, C, margin=-1.0)
    with pytest.raises(ValueError, match="method"):
        Bx.learn(X, Y, "svm", confusers=C)


def test_learn_refuses_a_model_that_left_the_data():
    """A run whose boxes no longer hold the training skin (here forced by a prohibitive width cost, which
    shrinks every box to nothing) is an error, not a silent detector that finds nothing. (A normal run's
    coverage, over seeds and thread counts: tests/test_reproducibility.py.)"""
    X, Y, C = diagonal(3000, seed=2)
    from torchskin.errors import Failure

    with pytest.raises(Failure, match="training failed"):  # a failure, not bad input (ValueError)
        Bx.learn(X, Y, confusers=C, steps=200, batch=1000, width_cost=50.0)


def test_coverage_training_is_deterministic():
    X, Y, C = diagonal(3000, seed=2)
    a = Bx.train_boxes(X, Y, C, steps=60, batch=1000).model.state_dict()
    b = Bx.train_boxes(X, Y, C, steps=60, batch=1000).model.state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_detector_edge_forms_equal_the_index_rules():
    """The division-free torch reference of detector.onnx (``BoxDetector``: edge forms) decides as the index rules
    (``ratio_indices`` + ``inside_box``) but on the edges, and its score is the weighted index margin."""
    g = torch.Generator().manual_seed(7)
    X, _ = synthetic(8, seed=3)
    model = Bx.BoxModel()
    cube = torch.rand(8, 4, 32, 32, generator=g) * 0.7
    cube[0, :, 0, 0] = 0.0  # undefined indices: never skin
    with torch.no_grad():
        mask, score = BoxDetector(model)(cube, X)
        box = model(X)[:, :, None, None]
    ndgri, ndsi, _ = ratio_indices(cube.movedim(1, -1))
    inside = Bx.inside_box(box, ndgri, ndsi)
    margin = torch.minimum(torch.minimum(ndgri - box[:, 0], box[:, 1] - ndgri),
                           torch.minimum(ndsi - box[:, 2], box[:, 3] - ndsi))
    differ = mask != inside
    assert bool((margin[differ].abs() < 1e-6).all()) and bool(mask.any()) and not bool(mask[0, 0, 0])
    # the score is the index margin weighted by the band-pair sum of the edge it is nearest to
    pair = torch.stack([cube[:, 0] + cube[:, 1], cube[:, 2] + cube[:, 3]], 1)
    m4 = torch.stack([ndgri - box[:, 0], box[:, 1] - ndgri, ndsi - box[:, 2], box[:, 3] - ndsi], 1)
    w4 = torch.stack([pair[:, 0], pair[:, 0], pair[:, 1], pair[:, 1]], 1)
    ok = pair.min(1).values > 0
    torch.testing.assert_close(score[ok], (m4 * w4).amin(1)[ok], atol=1e-6, rtol=1e-5)


def test_tiled_onboard_run_equals_one_call(trained, tmp_path):
    from torchskin.onboard import OnboardDetector

    X, _, res = trained
    paths = export(res.model, tmp_path)
    rng = np.random.default_rng(4)
    cube = (rng.random((2, 4, 96, 70)) * 0.7).astype(np.float32)
    cfg = X[:2].numpy().astype(np.float64)
    whole = OnboardDetector(paths["detector"], tile=1 << 20)(cube, cfg)
    tiled = OnboardDetector(paths["detector"], threads=3, tile=1024)(cube, cfg)  # 14 tiles, ragged last one
    # tiles evaluate the boxes of one frame at a time (batch 1), the single call all frames at once: onnxruntime's
    # Gemm may round the last bit differently for the two batch sizes
    assert np.array_equal(whole["mask"], tiled["mask"]) and np.allclose(whole["score"], tiled["score"], rtol=0, atol=1e-6)
    with torch.no_grad():
        mask_t, score_t = BoxDetector(res.model)(torch.from_numpy(cube), torch.from_numpy(cfg).float())
    assert np.abs(tiled["score"] - score_t.numpy()).max() < 1e-5 and tiled["mask"].any()
    det = OnboardDetector(paths["detector"], threads=2, tile=1024)
    out = (np.zeros((2, 96, 70), dtype=bool), np.zeros((2, 96, 70), dtype=np.float32))
    for _ in range(2):  # preallocated outputs, reused across frames
        r = det(cube, cfg, out=out)
        assert r["mask"] is out[0] and np.array_equal(out[0], tiled["mask"]) and np.array_equal(out[1], tiled["score"])
    small = OnboardDetector(paths["detector"])  # one-call path (frame smaller than a tile)
    out1 = (np.zeros((2, 96, 70), dtype=bool), np.zeros((2, 96, 70), dtype=np.float32))
    small(cube, cfg, out=out1)
    assert np.array_equal(out1[1], whole["score"])
    for bad in [(out[0],), (out[0][:, :-1], out[1]), (out[0], out[1].astype(np.float64)), (out[0], out[1][:, :, ::2])]:
        with pytest.raises(ValueError, match="out"):
            det(cube, cfg, out=bad)
    # tiles run the box graph split (edge matrices once per frame, the per-pixel head per tile): the same bits as
    # the whole graph run per tile, the brightness floor included
    assert tiled_det_is_split(paths["detector"])
    joined = OnboardDetector(paths["detector"], threads=2, tile=1024)
    joined._split = None
    for floor in (0.0, 0.3):
        a = OnboardDetector(paths["detector"], threads=2, tile=1024)(cube, cfg, min_reflectance=floor)
        b = joined(cube, cfg, min_reflectance=floor)
        assert np.array_equal(a["mask"], b["mask"]) and np.array_equal(a["score"], b["score"])
        want = (score_t.numpy() > 0) & (cube.sum(1) > 4 * floor)
        assert np.array_equal(a["mask"] | (np.abs(score_t.numpy()) < 1e-5), want | (np.abs(score_t.numpy()) < 1e-5))
    assert (OnboardDetector(paths["detector"], tile=1024)(cube, cfg, min_reflectance=0.3)["mask"]
            < tiled["mask"]).any()  # the floor removes dark pixels the boxes take
    late = cube.copy()
    late[1, 2, 90, 60] = np.nan  # in the last tile of the second frame
    with pytest.raises(ValueError, match="NaN"):
        OnboardDetector(paths["detector"], threads=2, tile=1024)(late, cfg)
    late[1, 2, 90, 60] = -0.01
    with pytest.raises(ValueError, match="negative"):
        OnboardDetector(paths["detector"], threads=2, tile=1024)(late, cfg)


def tiled_det_is_split(path) -> bool:
    from torchskin.onboard import OnboardDetector

    return OnboardDetector(path, tile=1024)._split is not None


@pytest.mark.parametrize("tile", [1024, 1 << 20])  # tiled on 2 workers (ragged last tile), and one call
def test_onboard_clips_negative_noise_only_when_asked(trained, tmp_path, tile):
    """negative="clip": the mask and score equal those of the cube with negatives set to 0, the count of
    clipped values per frame comes back, the caller's cube is untouched and NaN is still refused."""
    from torchskin.onboard import OnboardDetector

    X, _, res = trained
    paths = export(res.model, tmp_path)
    rng = np.random.default_rng(5)
    cube = (rng.random((2, 4, 96, 70)) * 0.7 - 0.05).astype(np.float32)  # ~7 % slightly negative values
    cube[1, 3, :10] = -0.2
    cfg = X[:2].numpy().astype(np.float64)
    det = OnboardDetector(paths["detector"], threads=2, tile=tile)
    with pytest.raises(ValueError, match="clip"):  # the error names the way out
        det(cube, cfg)
    before = cube.copy()
    got = det(cube, cfg, negative="clip")
    ref = det(np.maximum(cube, 0), cfg)
    assert np.array_equal(cube, before)
    assert np.array_equal(got["mask"], ref["mask"]) and np.array_equal(got["score"], ref["score"])
    assert got["clipped_values"].tolist() == [int((cube[b] < 0).sum()) for b in range(2)]
    assert "clipped_values" not in ref and got["mask"].any()
    nan = cube.copy()
    nan[1, 0, 95, 69] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        det(nan, cfg, negative="clip")
    with pytest.raises(ValueError, match="negative must be"):
        det(cube, cfg, negative="ignore")
    # a brightness floor: pixels at the noise floor (mean reflectance <= 0.2 here) are never skin
    dark = np.maximum(cube, 0)
    gated = det(dark, cfg, min_reflectance=0.2)
    bright = dark.mean(1) > 0.2
    assert np.array_equal(gated["mask"], ref["mask"] & bright) and 0 < (ref["mask"] & ~bright).sum()
    assert np.array_equal(gated["score"], ref["score"])  # the score stays the rules' margin
    with pytest.raises(ValueError, match="min_reflectance"):
        det(dark, cfg, min_reflectance=-0.1)


def test_ndvn_rule_in_the_detector_in_training_and_in_the_budget():
    """The visible/NIR rule NDVN >= d1: the divisionless detector applies it as a fifth edge form; learn()
    learns d1 just below the training skin's NDVN; a confuser that only that rule rejects no longer blocks the
    box, one that passes it still does; and the false-alarm budget lets a box hold `allow` confusers."""
    g = torch.Generator().manual_seed(11)
    n = 4000
    X = torch.stack([torch.rand(n, generator=g) * 80, torch.rand(n, generator=g) * 70,
                     torch.rand(n, generator=g) * 180], -1)
    Y = torch.stack([-0.3 + 0.08 * torch.randn(n, generator=g), 0.55 + 0.12 * torch.randn(n, generator=g),
                     0.05 * torch.randn(n, generator=g)], -1)
    dark = torch.tensor([[-0.3, 0.3, -0.6]])  # inside the skin's (NDGRI, NDSI) range, far darker in the visible
    flat = torch.tensor([[-0.3, 0.3, 0.0]])  # the same with skin's visible/NIR balance
    far = torch.tensor([[0.4, 0.0, 0.0], [-0.9, -0.1, 0.2]])
    model, info = Bx.learn(X, Y, confusers=torch.cat([dark, far]), steps=400, margin=0.02, width_cost=0.0)
    assert info["ndvn_learned"]
    with torch.no_grad():
        boxes = model(X[:50])
        d1_all = model(X)[:, 4]
    # NDVN does not depend on the configuration here: the learned d1 sits near the pooled quantile less the margin
    # (the pinball fit's error for 4000 pixels: well within 0.04), and just as many pixels fall below it
    pooled = float(torch.quantile(Y[:, 2].double(), Bx.NDVN_QUANTILE)) - Bx.NDVN_MARGIN
    assert float((d1_all - pooled).abs().max()) < 0.04
    assert float((Y[:, 2] < d1_all).float().mean()) < 3 * Bx.NDVN_QUANTILE
    assert bool((boxes[:, 2] < 0.3).all())  # the box reaches past the dark confuser: the rule keeps it out
    assert float(Bx.false_alarm_rate(boxes, dark).max()) == 0.0
    blocked, _ = Bx.learn(X, Y, confusers=torch.cat([flat, far]), steps=400, margin=0.02, width_cost=0.0)
    with torch.no_grad():
        assert float(Bx.false_alarm_rate(blocked(X[:50]), flat).max()) == 0.0  # that one must stay outside
    # the detector's fifth edge form is the NDVN margin times g + r + n + s
    cube = torch.rand(4, 4, 16, 16, generator=g) * 0.7
    with torch.no_grad():
        mask, score = BoxDetector(model)(cube, X[:4])
        box = model(X[:4])[:, :, None, None]
    ng, ns, nv = ratio_indices(cube.movedim(1, -1))
    inside = Bx.inside_box(box, ng, ns, nv)
    margin = torch.stack([ng - box[:, 0], box[:, 1] - ng, ns - box[:, 2], box[:, 3] - ns, nv - box[:, 4]]).abs()
    differ = mask != inside
    assert bool((margin.amin(0)[differ] < 1e-6).all()) and bool((~mask & (nv < box[:, 4])).sum() > 0)
    # the budget: the `allow` largest violations are free
    v = Bx.margin_violation(torch.tensor([[-0.5, 0.0, 0.2, 0.8]]), torch.tensor([[-0.3, 0.5], [-0.2, 0.4]]), 0.0)
    v1 = Bx.margin_violation(torch.tensor([[-0.5, 0.0, 0.2, 0.8]]), torch.tensor([[-0.3, 0.5], [-0.2, 0.4]]), 0.0, 1)
    assert float(v) == pytest.approx(0.2 + 0.2) and float(v1) == pytest.approx(0.2)


def test_learned_ndvn_rule_follows_the_configuration():
    """Skin whose NDVN falls with the sun (as level ELM panels under a blue sky make it at low sun): the learned d1
    follows it per configuration, where one pooled d1 would sit below the lowest sun's skin for every sun."""
    g = torch.Generator().manual_seed(5)
    n = 6000
    X = torch.stack([torch.rand(n, generator=g) * 80, torch.rand(n, generator=g) * 70,
                     torch.rand(n, generator=g) * 180], -1)
    v = 0.1 - 0.006 * X[:, 0] + 0.03 * torch.randn(n, generator=g)  # 0.1 at the zenith, -0.38 at 80°
    Y = torch.stack([-0.3 + 0.05 * torch.randn(n, generator=g), 0.6 + 0.05 * torch.randn(n, generator=g), v], -1)
    far = torch.tensor([[0.4, 0.0, 0.0], [-0.9, -0.1, 0.2]])
    model, info = Bx.learn(X, Y, confusers=far, steps=400, margin=0.02)
    with torch.no_grad():
        d1 = model(torch.tensor([[10.0, 35.0, 90.0], [70.0, 35.0, 90.0]]))[:, 4]
    # the conditional 1 % quantile of N(mu(sun), 0.03) less the margin: mu - 2.33 x 0.03 - 0.05
    want = torch.tensor([0.1 - 0.06, 0.1 - 0.42]) - 2.326 * 0.03 - Bx.NDVN_MARGIN
    assert float((d1 - want).abs().max()) < 0.04, (d1.tolist(), want.tolist())
    pooled = float(torch.quantile(v.double(), Bx.NDVN_QUANTILE)) - Bx.NDVN_MARGIN
    assert float(d1[0]) > pooled + 0.2  # a pooled rule would leave the high sun's d1 0.3 lower


def test_learn_holds_the_scene_budget_on_its_own_non_skin_pixels():
    """Scene non-skin pixels inside the skin's range, each with its configuration: learn() holds the share its
    own configuration's box calls skin within scene_budget (in training and the hard tuning), counting pixels
    below the brightness floor (NaN indices: load_scene_rows) in the denominator only."""
    g = torch.Generator().manual_seed(3)
    n = 4000
    X = torch.stack([torch.rand(n, generator=g) * 80, torch.rand(n, generator=g) * 70,
                     torch.rand(n, generator=g) * 180], -1)
    Y = torch.stack([-0.3 + 0.06 * torch.randn(n, generator=g), 0.6 + 0.06 * torch.randn(n, generator=g),
                     0.05 * torch.randn(n, generator=g)], -1)
    far = torch.tensor([[0.4, 0.0, 0.0], [-0.9, -0.1, 0.2]])
    # 2 % of the scene sits on the skin's NDSI edge at high sun only: a configuration-dependent intruder
    m = 3000
    Xs = torch.stack([torch.rand(m, generator=g) * 80, torch.rand(m, generator=g) * 70,
                      torch.rand(m, generator=g) * 180], -1)
    Ps = torch.tensor([[0.5, 0.0, 0.0]]).repeat(m, 1)
    k = (Xs[:, 0] < 30).nonzero().flatten()[:60]
    Ps[k] = torch.tensor([-0.3, 0.5, 0.0])
    Ps[-500:] = math.nan  # dark pixels: never detected, still counted
    free, _ = Bx.learn(X, Y, confusers=far, steps=300, margin=0.02)
    assert Bx.scene_rate(free, Xs, Ps) > 0.01  # without the scene the box reaches the intruders
    held, info = Bx.learn(X, Y, confusers=far, steps=300, margin=0.02, scene=(Xs, Ps), scene_budget=1e-3)
    rate = Bx.scene_rate(held, Xs, Ps)
    assert rate <= 1e-3 and info["pfa_scene_train"] == rate and info["scene_pixels"] == m
    assert info["train_coverage"] > 0.6  # the box gives up the intruders' corner, not the skin
    with pytest.raises(ValueError, match="scene_budget"):
        Bx.learn(X, Y, confusers=far, steps=1, scene=(Xs, Ps), scene_budget=1.0)
    with pytest.raises(ValueError, match="scene must be"):
        Bx.learn(X, Y, confusers=far, steps=1, scene=(Xs[:, :2], Ps))


def test_a_detector_reused_across_calls_gives_a_fresh_ones_bits(trained, tmp_path):
    """The tile buffers, bindings and weight buffers an OnboardDetector keeps between calls (``_TileBinding``)
    carry nothing from one call to the next: frames of other sizes (another ragged last tile), other
    configurations, batches and floors, in any order, give the bits of a detector made for each call."""
    from torchskin.onboard import OnboardDetector

    X, _, res = trained
    paths = export(res.model, tmp_path)
    rng = np.random.default_rng(3)
    cubes = [(rng.random((1, 4, 40, 52)) * 0.7).astype(np.float32),  # 2 tiles of 1024 and a ragged one of 32
             (rng.random((2, 4, 37, 61)) * 0.7).astype(np.float32)]  # a ragged 209 per frame
    calls = [(0, 0, 0.0), (1, 1, 0.05), (0, 2, 0.05), (1, 3, 0.3), (0, 0, 0.0)]
    kept = OnboardDetector(paths["detector"], threads=2, tile=1024)
    for cube_k, cfg_k, floor in calls:
        cube = cubes[cube_k]
        cfg = X[cfg_k:cfg_k + len(cube)].numpy().astype(np.float64)
        a = kept(cube, cfg, min_reflectance=floor)
        b = OnboardDetector(paths["detector"], threads=2, tile=1024)(cube, cfg, min_reflectance=floor)
        assert np.array_equal(a["mask"], b["mask"]) and np.array_equal(a["score"], b["score"])
    assert len({float(v) for v in X[:4, 0]}) > 1  # the configurations differ


def test_tile_head_takes_every_path_with_the_whole_graphs_bits(trained, tmp_path):
    """The rebuilt per-tile head (``onboard.heads._EdgeHead``: two-band MatMuls for L1-L4, the minimum in numpy, the
    floor skipped, gathered or summed by tile) gives the bits of the whole graph run per tile, on tiles with no
    skin, a few skin pixels and many, and tiles that fail the one-pass range check (a glint above
    REFLECTANCE_MAX, -0.0)."""
    from torchskin.onboard import REFLECTANCE_MAX, OnboardDetector

    X, _, res = trained
    paths = export(res.model, tmp_path)
    det = OnboardDetector(paths["detector"], threads=2, tile=1024)
    assert det._split is not None and det._split[1].groups == ["gr", "gr", "ns", "ns", "all"]
    joined = OnboardDetector(paths["detector"], threads=2, tile=1024)
    joined._split = None
    cfg = X[:1].numpy().astype(np.float64)
    rng = np.random.default_rng(7)
    cube = (rng.random((1, 4, 64, 96)) * 0.7).astype(np.float32)  # 6 tiles of 1024 pixels
    skin = det(cube, cfg)["mask"].reshape(-1)
    flat = cube.reshape(4, -1)
    inside = np.flatnonzero(skin)
    assert len(inside) > 10
    # tile 0 all skin: skin pixels' spectra scaled (the same indices, so inside the boxes) to mean reflectance
    # 0.02-0.6, which the floors 0.05 and 0.3 split
    pick = rng.choice(inside, 1024)
    scale = rng.uniform(0.02, 0.6, 1024) / cube.reshape(4, -1)[:, pick].mean(0)
    cube.reshape(4, -1)[:, :1024] = (cube.reshape(4, -1)[:, pick] * scale).astype(np.float32)
    inside = np.flatnonzero(det(cube, cfg)["mask"].reshape(-1))
    flat[:, 1024:2048] = 0.5  # equal bands: NDGRI = NDSI = 0, taken by no learned box -> a tile without skin
    flat[:, 2048:3072] = 0.5
    flat[:, 2048:2058] = flat[:, inside[:10]]  # a tile with few skin pixels
    flat[0, 3100] = REFLECTANCE_MAX * 1.01  # a glint: the slow check, still a valid cube
    flat[1, 4200] = -0.0  # sign bit set: the slow check, not negative
    # tile 5 all bright skin (1080 nm reflectance 0.25-0.6): that band alone above the 0.05 floor (on the sum,
    # 0.2) everywhere, so the floor is skipped there, and not above the 0.3 one (1.2), which is computed
    pick = rng.choice(inside, 1024)
    flat[:, 5120:6144] = (flat[:, pick] * rng.uniform(0.25, 0.6, 1024) / flat[2, pick]).astype(np.float32)
    assert flat[2, 5120:6144].min() > 4 * 0.05 and not flat[2, 5120:6144].min() > 4 * 0.3
    assert 16 * det(cube, cfg)["mask"].reshape(-1)[5120:6144].sum() > 1024  # dense: not the few-pixel path
    for floor in (0.0, 0.05, 0.3):
        a, b = det(cube, cfg, min_reflectance=floor), joined(cube, cfg, min_reflectance=floor)
        assert np.array_equal(a["mask"], b["mask"]) and np.array_equal(a["score"], b["score"])
        assert np.array_equal(a["mask"], (b["score"] > 0) & (cube.sum(1) > 4 * floor))  # the floor by its definition
    m = det(cube, cfg, min_reflectance=0.0)["mask"].reshape(-1)
    assert not m[1024:2048].any() and 0 < m[2048:3072].sum() <= 10 and m[:1024].sum() > 900
