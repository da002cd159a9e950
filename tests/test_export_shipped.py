"""The shipped default models in exports/: re-exporting the committed checkpoints reproduces the committed ONNX
files and model cards, their metadata are complete, the three exports run through `torchskin evaluate`, and
the shipped detector meets the held-out and fresh-test figures it claims."""

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from torchskin.cli import main
from torchskin.detectors import boxes as Bx
from torchskin.detectors.features import confuser_indices, tuning_configs

EXPORTS = Path(__file__).resolve().parents[1] / "exports"
FILES = ("boundaries.pt", "baseline_box.pt", "classifier.pt", "boundaries.onnx", "baseline_box.onnx", "detector.onnx",
         "boundaries.md", "baseline_box.md", "detector.md", "evaluation.json", "evaluation_test.json", "selection.json")


@pytest.fixture(scope="module")
def committed():
    for f in FILES:
        assert (EXPORTS / f).is_file(), f"exports/{f} is missing: run `make demo`"
    return (Bx.load(EXPORTS / "boundaries.pt"), json.loads((EXPORTS / "evaluation.json").read_text()),
            json.loads((EXPORTS / "selection.json").read_text()))


@pytest.fixture(scope="module")
def reexported(committed, tmp_path_factory):
    """The pipeline's export step repeated from the committed checkpoints into a fresh folder."""
    _, _, sel = committed
    out = tmp_path_factory.mktemp("reexport")
    assert main(["export", "--model", str(EXPORTS / "boundaries.pt"), "--baseline", str(EXPORTS / "baseline_box.pt"),
                 "--detector", str(EXPORTS / sel["detector"]), "--detector-reason", sel["reason"], "--out", str(out),
                 "--metrics", str(EXPORTS / "evaluation.json")]) == 0
    return out


def test_reexport_reproduces_the_committed_onnx_and_cards(committed, reexported):
    from torchskin.onboard import OnboardBoxes, OnboardDetector

    model, _, _ = committed
    lo, hi = model.domain[:, 0], model.domain[:, 1]
    cfg = (lo + (hi - lo) * torch.rand(2000, 3, generator=torch.Generator().manual_seed(1))).numpy()
    for name in ("boundaries", "baseline_box"):
        old, new = OnboardBoxes(EXPORTS / f"{name}.onnx")(cfg), OnboardBoxes(reexported / f"{name}.onnx")(cfg)
        assert np.abs(old["boxes"] - new["boxes"]).max() < 1e-6
        with torch.no_grad():
            assert np.abs(old["boxes"] - Bx.load(EXPORTS / f"{name}.pt")(torch.from_numpy(cfg)).numpy()).max() < 1e-5
    rng = np.random.default_rng(2)
    cube = (rng.random((2, 4, 40, 50)) * 0.6).astype(np.float32)
    from torchskin import tissue  # the Type I/II preset's diffuse reflectance in the index bands: a skin spectrum

    skin = tissue.reflectance(tissue.preset("I-II"), torch.tensor([544.0, 633.0, 1080.0, 1580.0], dtype=torch.float64))
    cube[:, :, 10:30, 10:30] = skin.reshape(4).float().numpy()[:, None, None]
    dcfg = np.concatenate([cfg[:2], [[0.2], [0.6]]], 1)  # the shipped lookup table also takes the diffuse share
    a = OnboardDetector(EXPORTS / "detector.onnx")(cube, dcfg)
    b = OnboardDetector(reexported / "detector.onnx")(cube, dcfg)
    assert np.array_equal(a["score"], b["score"]) and a["mask"][:, 10:30, 10:30].all()
    for card in ("boundaries.md", "baseline_box.md", "detector.md"):  # a pure function of checkpoint + evaluation
        assert (reexported / card).read_text() == (EXPORTS / card).read_text(), card
    import onnx

    for name in ("boundaries", "baseline_box", "detector"):  # the committed graphs carry today's metadata (kind, bands)
        meta = [{p.key: p.value for p in onnx.load(str(d / f"{name}.onnx")).metadata_props} for d in (EXPORTS, reexported)]
        assert meta[0] == meta[1] and meta[0]["kind"] == ("lut" if name == "detector" else "boxes"), name


def test_committed_metadata_and_cards(committed):
    import onnx

    model, ev, sel = committed
    for name in ("boundaries", "baseline_box", "detector"):
        m = onnx.load(str(EXPORTS / f"{name}.onnx"))
        onnx.checker.check_model(m, full_check=True)
        meta = {p.key: p.value for p in m.metadata_props}
        assert m.opset_import[0].version >= 17 and meta["skin_surface_model"] == "thesis"
        angles = [[0.0, 89.0], [0.0, 90.0], [0.0, 180.0]]  # the box graphs; the lookup table adds the diffuse share
        extra = (["diffuse_share"], [[0.0, 1.0]]) if name == "detector" else ([], [])
        assert json.loads(meta["features"]) == list(model.features) + extra[0]
        assert json.loads(meta["feature_domain"]) == model.domain.tolist() + extra[1] == angles + extra[1]
        assert json.loads(meta["bands_nm"]) == [544.0, 633.0, 1080.0, 1580.0] and len(meta["training_manifest_sha256"]) == 64
        card = (EXPORTS / f"{name}.md").read_text()
        for section in ("## Intended use", "## Training data", "## Evaluation", "## Limits"):
            assert section in card
        assert meta["training_manifest_sha256"] in card and "`thesis` skin surface model" in card
        entry = next(x for x in ev["models"] if x["name"] == meta.get("checkpoint", ""))
        assert f"{entry['overall']['pd_sunlit']:.3f}" in card
    det = {p.key: p.value for p in onnx.load(str(EXPORTS / "detector.onnx")).metadata_props}
    assert det["detector_model"] == sel["detector"] and float(det["min_reflectance"]) == ev["min_reflectance"]
    assert sel["reason"] in (EXPORTS / "detector.md").read_text()


def test_shipped_models_meet_their_claims(committed):
    """Held-out (used to calibrate and choose) and fresh test set (seed 3, used for nothing else): the committed
    figures claim the shipped detector within the false-alarm budgets, its sunlit Pd well above the static box's
    and above the single refitted box's at the same budgets (README: 0.770, 0.488, 0.689)
    (measured again on a regenerated slice of the test set in
    ``test_shipped_detector_claims_hold_on_a_regenerated_test_slice``); every committed box model keeps the
    earthlib test spectra out over its whole training domain."""
    from torchskin.evaluation import select_detector

    _, ev, sel = committed
    assert select_detector(ev)[0] == sel["detector"]  # the choice follows from the committed evaluation
    test = json.loads((EXPORTS / "evaluation_test.json").read_text())
    names = [m["name"] for m in test["models"]]
    # the exports, then the pipeline's checkpoints that are not exported (scripts/pipeline_export.py), the static box
    assert names == ["boundaries.onnx", "baseline_box.onnx", "detector.onnx", "classifier.pt", "static box (thesis)"]
    det, static = test["models"][2]["overall"], test["models"][-1]["overall"]
    # 960 drawn; the frames whose empirical line is physical (elm_valid) are evaluated: 762 (the rest have
    # unlit or shadowed panels, no line, or panels lit less than a third of what a sun-facing surface gets)
    assert test["configurations"] >= 700
    assert det["pfa"] <= 1e-3 and det["pfa_scene"] <= 1e-4  # the budgets the card claims
    assert det["pd_sunlit"] - static["pd_sunlit"] >= 0.25 and det["pd_shadow"] - static["pd_shadow"] >= 0.15
    assert det["pd_sunlit"] > test["models"][1]["overall"]["pd_sunlit"]  # the single box, calibrated alike
    for m in ev["models"]:  # every model was calibrated to the budgets on the held-out set before the choice
        if m["kind"] != "static":
            assert m["overall"]["pfa_scene"] <= 1e-4 and m["overall"]["pfa"] <= 1e-3, m["name"]
    for name in ("boundaries.pt", "baseline_box.pt"):
        model = Bx.load(EXPORTS / name)
        grid = tuning_configs(model, torch.zeros(0, 3), grid=8)
        with torch.no_grad():
            pfa = Bx.false_alarm_rate(model(grid), confuser_indices("test"))
        assert float(pfa.max()) <= 1e-3, name


#: shards of the fresh test set regenerated for the measured claims (4 pose groups x 48 configurations each)
TEST_SLICE_SHARDS = 2


@pytest.mark.anny
@pytest.mark.slow
def test_shipped_detector_claims_hold_on_a_regenerated_test_slice(tmp_path):
    """The fresh-test figures of evaluation_test.json, measured: the first shards of the same test set (seed 3,
    earthlib test partition for confusers and clothing, default configuration, as scripts/pipeline_generate.py
    makes it; a shard is a pure function of config, seed and index) regenerated, and detector.onnx evaluated on
    them. Its sunlit Pd agrees with the claim within sampling error, and its false alarms stay in budget."""
    import pandas as pd

    from torchskin.dataset.config import resolve_config
    from torchskin.dataset.generate import generate
    from torchskin.evaluation import evaluate

    claim = json.loads((EXPORTS / "evaluation_test.json").read_text())
    claimed = {m["name"]: m["overall"] for m in claim["models"]}
    cfg = resolve_config({"confusers": {"partition": "test"}, "clothing": {"partition": "test"}})
    per_shard = cfg["sun"]["per_pose"] * cfg["skin"]["per_pose"] * cfg["sampling"]["groups_per_shard"]
    man = generate(cfg, TEST_SLICE_SHARDS * per_shard, 3, tmp_path / "test", quiet=True)
    assert man["n_shards"] == TEST_SLICE_SHARDS
    r = evaluate(tmp_path / "test", [str(EXPORTS / "detector.onnx")])
    det, static = r["models"][0]["overall"], r["models"][-1]["overall"]
    df = pd.read_parquet(tmp_path / "test")
    lit = df[df.elm_valid & df.label & ~df.shadow]
    assert det["sunlit_skin_pixels"] == len(lit) > 5000
    n_cfg = lit.groupby(["group", "sun", "skin"]).ngroups  # configurations with sunlit skin
    # Sampling error of a sunlit Pd p: the pixels of one configuration (one skin under one sun and view) are
    # strongly correlated, so the configuration is the sampling unit; with every configuration's pixels fully
    # correlated the variance is p (1 - p) / n_cfg, an upper bound for partial correlation. The claim comes from
    # the full test set (claim["configurations"]), written before the dataset code last changed the bytes: the
    # two Pd are taken as independent samples (what a cross-machine comparison also is), variances added.
    for name, got in (("detector.onnx", det), ("static box (thesis)", static)):
        p = claimed[name]["pd_sunlit"]
        se = math.sqrt(p * (1 - p) * (1 / n_cfg + 1 / claim["configurations"]))
        assert abs(got["pd_sunlit"] - p) <= 4 * se, (name, got["pd_sunlit"], p, se)
    assert det["pd_sunlit"] - static["pd_sunlit"] >= 0.2  # far above the static box
    # the false-alarm budgets of the selection: earthlib test spectra per configuration; the scene's non-skin
    # pixels as a count, no more than a Poisson draw at the budget's rate would give (99.9 %: a slice of ~25 k
    # pixels expects 2.5 at 1e-4)
    n = det["nonskin_pixels"]
    lam, k, cdf, term = 1e-4 * n, 0, 0.0, math.exp(-1e-4 * n)
    while cdf + term < 0.999:
        cdf, k, term = cdf + term, k + 1, term * lam / (k + 1)
    assert det["pfa"] <= 1e-3 and round(det["pfa_scene"] * n) <= k, (det["pfa_scene"] * n, k)


@pytest.mark.slow
def test_evaluate_runs_the_three_exports(tmp_path, capsys):
    """`torchskin evaluate` on boundaries.onnx, baseline_box.onnx and detector.onnx over a small generated
    dataset: one table row and one JSON entry each; detector.onnx (run on the pixels as a B x 4 x 1 x 1 cube)
    decides as the box model it was made from."""
    from torchskin.dataset.config import resolve_config
    from torchskin.dataset.generate import generate
    from torchskin.evaluation import evaluate
    from torchskin.render.meshes import sphere_mesh, write_obj

    v, f = sphere_mesh(0.35, 3)
    obj = tmp_path / "head.obj"
    write_obj(obj, v + [0.0, 0.0, 0.9], f)
    cfg = resolve_config({"camera": {"width": 64, "height": 64, "range_m": [5.0, 10.0]}, "sun": {"per_pose": 4},
                          "skin": {"per_pose": 2}, "subject": {"meshes": [str(obj)]},
                          "sampling": {"groups_per_shard": 2, "pixels_per_class": 32},
                          "confusers": {"partition": "test"}, "clothing": {"partition": "test"}})
    generate(cfg, 32, 7, tmp_path / "ds", quiet=True)
    paths = [str(EXPORTS / f"{n}.onnx") for n in ("boundaries", "baseline_box", "detector")]
    r = evaluate(tmp_path / "ds", paths)
    assert [m["kind"] for m in r["models"]] == ["boxes", "boxes", "detector", "static"]
    sel = json.loads((EXPORTS / "selection.json").read_text())
    source = {"boundaries.pt": 0, "baseline_box.pt": 1}.get(sel["detector"])
    if source is not None:
        a, b = r["models"][source]["overall"], r["models"][2]["overall"]
        for k in ("pd", "pd_sunlit", "pd_shadow", "pfa_scene", "pfa"):
            assert b[k] == pytest.approx(a[k], abs=2e-3), k
    # boundaries.onnx's sunlit Pd and mean box area recomputed from the Parquet rows, without evaluate: each
    # sunlit skin row's box from the ONNX graph, the rules (b1 <= NDGRI <= b2, c1 <= NDSI <= c2, NDVN >= d1)
    # and the brightness floor in float64 numpy from the row's reflectance; the box area per configuration
    ref = reference_box_figures(tmp_path / "ds", EXPORTS / "boundaries.onnx", r["min_reflectance"])
    got = r["models"][0]
    assert got["overall"]["sunlit_skin_pixels"] == ref["sunlit"] > 100
    # float32 (evaluate) and float64 (here) indices may decide differently only within 1e-6 of an edge
    assert abs(got["overall"]["pd_sunlit"] * ref["sunlit"] - ref["hits"]) <= ref["at_edge"] + 1e-6 * ref["sunlit"]
    assert r["configurations"] == ref["configurations"]
    assert got["area"]["mean"] == pytest.approx(ref["area_mean"], rel=1e-6)  # float32 box edges
    # detector.onnx's area is counted on evaluate's AREA_GRID grid over [-1, 1]²: each edge of a box is off by
    # at most one cell δ = 2 / AREA_GRID, so the area by at most δ (w + h) + δ² against the box model's w h
    from torchskin.evaluation.regions import AREA_GRID

    if source == 0:
        delta = 2.0 / AREA_GRID
        bound = delta * ref["perimeter_mean"] / 2 + delta ** 2
        assert abs(r["models"][2]["area"]["mean"] - got["area"]["mean"]) <= bound
    assert main(["evaluate", "--data", str(tmp_path / "ds"), *[x for p in paths for x in ("--model", p)], "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert len(doc["models"]) == 4


@pytest.mark.anny
@pytest.mark.slow
def test_shipped_detector_finds_sunlit_skin_in_the_thesis_geometry(tmp_path):
    """The flagship case end to end: the thesis geometry (horizontal camera at 9.449 m, Type I/II subject,
    panels beside it, sun 45° up and 20° round), rendered with sensor noise under the thesis's surface model,
    calibrated from the signal frame with the onboard ELM through the panels' pixel regions, then the shipped
    detector.onnx. The static box misses the skin seen at grazing incidence; the shipped detector keeps nearly
    all sunlit skin, and with its brightness floor no pixel off the subject passes."""
    from torchskin.evaluation import thesis_frame

    r = thesis_frame(EXPORTS / "detector.onnx", plot=tmp_path / "thesis.png")
    assert (tmp_path / "thesis.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert r["sunlit_skin_pixels"] > 100 and not r["out_of_domain"] and r["elm_max_diff"] < 1e-3
    assert r["pd_sunlit_learned"] > 0.9 and r["pd_sunlit_learned"] > r["pd_sunlit_static"] + 0.2
    assert r["false_alarms_learned"] == 0


def reference_box_figures(data_dir, onnx_path, floor: float) -> dict:
    """Sunlit skin hits and box areas of a boundaries ONNX on a dataset, computed in numpy from the rows."""
    import pandas as pd

    from torchskin.onboard import OnboardBoxes

    df = pd.read_parquet(data_dir)
    df = df[df.elm_valid].reset_index(drop=True)
    b = OnboardBoxes(onnx_path)
    X = df[list(b.features)].to_numpy(np.float32)
    box = b(X)["boxes"].astype(np.float64)
    g_, r_, n_, s_ = (df[c].to_numpy(np.float64) for c in ("r544", "r633", "r1080", "r1580"))
    ndgri, ndsi, ndvn = (g_ - r_) / (g_ + r_), (n_ - s_) / (n_ + s_), ((g_ + r_) - (n_ + s_)) / (g_ + r_ + n_ + s_)
    inside = (ndgri >= box[:, 0]) & (ndgri <= box[:, 1]) & (ndsi >= box[:, 2]) & (ndsi <= box[:, 3])
    if box.shape[1] > 4:
        inside &= ndvn >= box[:, 4]
    hit = inside & ((g_ + r_ + n_ + s_) / 4 > floor)
    edges = np.concatenate([np.abs(ndgri[:, None] - box[:, :2]), np.abs(ndsi[:, None] - box[:, 2:4]),
                            np.abs(ndvn[:, None] - box[:, 4:])], 1).min(1)
    sunlit = (df.label & ~df.shadow).to_numpy()
    first = df.groupby(["group", "sun", "skin"]).head(1).index.to_numpy()  # one row per configuration
    c = np.clip(box[first, :4], -1, 1)
    w, h = np.clip(c[:, 1] - c[:, 0], 0, None), np.clip(c[:, 3] - c[:, 2], 0, None)
    return {"sunlit": int(sunlit.sum()), "hits": int((hit & sunlit).sum()),
            "at_edge": int((sunlit & (edges < 1e-6)).sum()), "configurations": len(first),
            "area_mean": float((w * h).mean()), "perimeter_mean": float((2 * (w + h)).mean())}


def test_selection_ships_only_graphs_that_meet_the_onboard_budget():
    """A classifier with the highest Pd inside the budgets is reported, not shipped, while a box model is
    eligible (its per-pixel MLP is ~40x the box graph's onboard time); with no box model, or when its kind is
    allowed, it is chosen. A lookup table (onboard within the budget) with the highest Pd is shipped."""
    from torchskin.evaluation import ONBOARD_KINDS, select_detector

    def model(name, kind, pd, pfa=0.0, scene=0.0, area=0.3):
        return {"name": name, "kind": kind, "overall": {"pd_sunlit": pd, "pfa": pfa, "pfa_scene": scene},
                "area": {"mean": area}}

    boxes, clf = model("b.pt", "boxes", 0.962), model("c.pt", "classifier", 0.984, 3e-5, 4e-5, 0.8)
    static = model("static box (thesis)", "static", 0.465)
    assert ONBOARD_KINDS == ("boxes", "lut")
    name, why = select_detector({"models": [boxes, clf, static]})
    assert name == "b.pt" and "onboard cost" in why and "c.pt" in why.split("onboard cost")[1]
    assert select_detector({"models": [boxes, clf, static]}, onboard_kinds=("boxes", "classifier"))[0] == "c.pt"
    assert select_detector({"models": [clf, static]})[0] == "c.pt"  # nothing meets the onboard budget: best Pd
    lut = model("l.pt", "lut", 0.988, 0.0, 5e-5, 0.4)
    name, why = select_detector({"models": [boxes, clf, lut, static]})
    costly = why.split("onboard cost")[1].split("Held-out")[0]
    assert name == "l.pt" and "c.pt" in costly and "l.pt" not in costly
    # within the Pd tolerance a box model with the smaller region wins, whatever the order
    other = model("b2.pt", "boxes", 0.960, area=0.25)
    assert select_detector({"models": [boxes, other, static]})[0] == "b2.pt"


def test_the_packaged_detector_is_the_shipped_one():
    """pip users get ``torchskin/data/detector.onnx`` (package data; ``detect``'s default model): it must be the
    committed ``exports/detector.onnx`` byte for byte (``make demo``'s export step copies it)."""
    from torchskin.onboard import SHIPPED_DETECTOR

    packaged = Path(SHIPPED_DETECTOR)
    assert packaged == Path(__file__).resolve().parents[1] / "torchskin" / "data" / "detector.onnx"
    assert packaged.read_bytes() == (EXPORTS / "detector.onnx").read_bytes(), \
        "torchskin/data/detector.onnx differs from exports/detector.onnx: copy it (scripts/pipeline_export.py does)"
