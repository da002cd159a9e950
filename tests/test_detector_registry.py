"""The detector kinds' registry: checkpoints carry their kind (old box checkpoints without one still load), the
training settings are dataclasses, and a new kind is one class plus one ``register`` call that ``evaluate``,
``export``, the model cards and ``torchskin train`` then handle like the built-in ones."""

from pathlib import Path
from typing import ClassVar

import numpy as np
import pytest
import torch
from test_boundaries_onnx import diagonal  # the synthetic skin walk of the box tests
from torch import nn

from torchskin.detectors import registry
from torchskin.detectors.boxes import BoxModel, BoxTraining, train_boxes
from torchskin.detectors.classifier import ClassifierTraining, SkinClassifier, train_classifier
from torchskin.detectors.features import FEATURES, MIN_REFLECTANCE, config_buffers, ratio_indices
from torchskin.detectors.graphs import torch_detector_graph
from torchskin.detectors.protocol import BoxDetectorModel, DetectorModel, TrainRequest

EXPORTS = Path(__file__).resolve().parents[1] / "exports"


class NdsiThresholdDetector(nn.Module):
    """The toy kind's ``detector.onnx``: score = (n - s) - t (n + s), positive where NDSI > t (division-free, as
    the box kind's edge forms)."""

    def __init__(self, t: torch.Tensor):
        super().__init__()
        self.t = t

    def forward(self, cube: torch.Tensor, config: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        n, s = cube[:, 2], cube[:, 3]
        score = (n - s) - self.t * (n + s)
        return score > 0, score


class NdsiThreshold(nn.Module):
    """A toy detector kind: skin where NDSI > ``threshold``, whatever the configuration."""

    kind: ClassVar[str] = "ndsi_threshold"
    methods: ClassVar[tuple[str, ...]] = ("ndsi_threshold",)
    threshold: torch.Tensor
    domain: torch.Tensor

    def __init__(self, threshold: float = 0.5, features=FEATURES):
        super().__init__()
        self.features = tuple(features)
        self.register_buffer("threshold", torch.tensor(float(threshold)))
        self.register_buffer("domain", config_buffers(self.features)[2])

    def decide(self, R, config):
        R = torch.as_tensor(R, dtype=torch.float32)
        n, s = R[:, 2], R[:, 3]
        return (n - s) - self.threshold * (n + s) > 0

    def detector_graph(self, meta):
        return torch_detector_graph(NdsiThresholdDetector(self.threshold), len(self.features), meta)

    def checkpoint(self, meta):
        return {"state_dict": self.state_dict(), "features": list(self.features), "meta": meta}

    @classmethod
    def from_checkpoint(cls, ck):
        m = cls(features=ck["features"])
        m.load_state_dict(ck["state_dict"])
        return m.eval()


@pytest.fixture
def toy_kind():
    registry.register(NdsiThreshold)
    yield NdsiThreshold
    registry.unregister("ndsi_threshold")


def test_builtin_kinds_and_their_methods():
    assert set(registry.kinds()) >= {"boxes", "classifier"}
    assert registry.methods()[:3] == ("boxes", "quantiles", "classifier")
    assert registry.kind_for_method("quantiles") is BoxModel
    assert registry.kind_for_method("classifier") is SkinClassifier
    assert registry.kind_for_method(None) is BoxModel  # the cards' rule: a box model unless told otherwise
    with pytest.raises(ValueError, match="unknown training method 'svm'"):
        registry.kind_for_method("svm", default=None)
    assert registry.kind_of(BoxModel()) == "boxes" and registry.kind_of(SkinClassifier()) == "classifier"
    with pytest.raises(ValueError, match="not a registered detector kind"):
        registry.kind_of(nn.Linear(2, 2))
    assert isinstance(BoxModel(), BoxDetectorModel) and registry.boxes_of(BoxModel()) is not None
    assert isinstance(SkinClassifier(), DetectorModel) and registry.boxes_of(SkinClassifier()) is None


def test_register_refuses_taken_names_and_incomplete_kinds(toy_kind):
    class Again(NdsiThreshold):
        pass

    with pytest.raises(ValueError, match="already registered"):
        registry.register(Again)

    class Clash(NdsiThreshold):
        kind = "clash"
        methods = ("boxes",)

    with pytest.raises(ValueError, match="boxes of kind 'clash' already belong to boxes"):
        registry.register(Clash)

    class Half:
        kind = "half"
        methods = ()

        def decide(self, R, config):
            return R[:, 0] > 0

    with pytest.raises(ValueError, match="lacks detector_graph, checkpoint, from_checkpoint"):
        registry.register(Half)  # type: ignore[arg-type]
    assert "half" not in registry.kinds() and "clash" not in registry.kinds()


def test_checkpoints_carry_their_kind_and_old_ones_still_load(tmp_path):
    shipped = torch.load(EXPORTS / "boundaries.pt", map_location="cpu", weights_only=True)
    assert shipped["kind"] == "boxes"
    old = {k: v for k, v in shipped.items() if k != "kind"}  # a box checkpoint written before the key existed
    torch.save(old, tmp_path / "old.pt")
    model, ck = registry.load(tmp_path / "old.pt")
    assert registry.kind_of(model) == "boxes" and ck is not None
    assert torch.equal(model.boxes(torch.tensor([[30.0, 40.0, 90.0]])),
                       registry.load(EXPORTS / "boundaries.pt")[0].boxes(torch.tensor([[30.0, 40.0, 90.0]])))
    clf, ck = registry.load(EXPORTS / "classifier.pt")
    assert registry.kind_of(clf) == "classifier" and ck["kind"] == "classifier"
    registry.save(model, tmp_path / "b.pt", {"note": 1})
    again = torch.load(tmp_path / "b.pt", map_location="cpu", weights_only=True)
    assert again["kind"] == "boxes" and again["meta"] == {"note": 1}
    back, _ = registry.load(tmp_path / "b.pt")
    cfg = torch.tensor([[30.0, 40.0, 90.0], [70.0, 10.0, 170.0]])
    assert torch.equal(back.boxes(cfg), model.boxes(cfg))
    # the box kind's own save writes the same bytes as the registry's
    from torchskin.detectors import boxes

    boxes.save(model, tmp_path / "b2.pt", {"note": 1})
    assert (tmp_path / "b2.pt").read_bytes() == (tmp_path / "b.pt").read_bytes()
    torch.save({**again, "kind": "svm"}, tmp_path / "svm.pt")
    with pytest.raises(ValueError, match="--model .*svm.pt' is a checkpoint of an unknown detector kind 'svm'"):
        registry.load(tmp_path / "svm.pt", "--model")
    with pytest.raises(ValueError, match="not a torchskin model checkpoint"):
        torch.save({"state_dict": {}}, tmp_path / "empty.pt")
        registry.load(tmp_path / "empty.pt")


def test_decide_is_the_rules_on_the_pixels_indices():
    model, _ = registry.load(EXPORTS / "boundaries.pt")
    g = torch.Generator().manual_seed(0)
    R = torch.rand(500, 4, generator=g) * 0.6
    X = torch.stack([torch.rand(500, generator=g) * 80, torch.rand(500, generator=g) * 80,
                     torch.rand(500, generator=g) * 180], -1)
    ng, ns, nv = ratio_indices(R)
    box = model(X)
    want = (ng >= box[:, 0]) & (ng <= box[:, 1]) & (ns >= box[:, 2]) & (ns <= box[:, 3]) & (nv >= box[:, 4])
    assert torch.equal(model.decide(R, X), want)


def test_training_settings_are_dataclasses_and_the_keyword_call_still_works():
    X, Y, C = diagonal(3000, 2)
    a = train_boxes(X, Y, C, BoxTraining(steps=30, batch=1000, hidden=8)).model.state_dict()
    b = train_boxes(X, Y, C, steps=30, batch=1000, hidden=8).model.state_dict()
    c = train_boxes(X, Y, C, BoxTraining(steps=30, hidden=8), batch=1000).model.state_dict()
    assert all(torch.equal(a[k], b[k]) and torch.equal(a[k], c[k]) for k in a)
    with pytest.raises(TypeError, match="unexpected option.*stepz"):
        train_boxes(X, Y, C, stepz=3)
    with pytest.raises(TypeError, match="unexpected option.*widht"):
        train_classifier(X, torch.rand(len(X), 4), torch.ones(len(X), dtype=torch.bool),
                         torch.ones(len(X), dtype=torch.bool), widht=3)
    assert ClassifierTraining().with_options(hidden=8).hidden == 8 and ClassifierTraining().hidden == 32


@pytest.mark.slow
def test_a_new_kind_runs_through_evaluate_export_and_the_cards(toy_kind, tiny_dataset, tmp_path):
    """The toy kind (NDSI > 0.5) registered in one call: ``evaluate`` judges its checkpoint by its own decisions,
    ``export`` writes its detector.onnx, which onnxruntime runs to the same decisions, and which ``evaluate`` judges
    to the same figures."""
    import onnxruntime as ort

    from torchskin.dataset.files import read_valid
    from torchskin.evaluation import evaluate
    from torchskin.export import export, write_model_cards

    toy = NdsiThreshold(0.5)
    registry.save(toy, tmp_path / "toy.pt", {"method": "ndsi_threshold"})
    r = evaluate(tiny_dataset, [tmp_path / "toy.pt", EXPORTS / "boundaries.pt"])
    assert [m["kind"] for m in r["models"]] == ["ndsi_threshold", "boxes", "static"]
    # its sunlit Pd, recomputed from the rows without evaluate
    t, _ = read_valid(tiny_dataset, ["r544", "r633", "r1080", "r1580", "label", "shadow", *FEATURES])
    col = {c: t.column(c).to_numpy(zero_copy_only=False) for c in t.column_names}
    R = torch.from_numpy(np.stack([col[c] for c in ("r544", "r633", "r1080", "r1580")], -1).astype(np.float32))
    X = torch.from_numpy(np.stack([col[f] for f in FEATURES], -1).astype(np.float32))
    lit = torch.from_numpy(col["label"] & ~col["shadow"])
    hit = toy.decide(R, X) & (R.mean(-1) > MIN_REFLECTANCE)
    assert int(lit.sum()) > 50
    assert r["models"][0]["overall"]["pd_sunlit"] == pytest.approx(float(hit[lit].float().mean()), abs=1e-12)
    assert 0.0 < r["models"][0]["overall"]["pd_sunlit"] < 1.0  # the test can tell a wrong decision

    baseline, _ = registry.load(EXPORTS / "baseline_box.pt")
    paths = export(baseline, tmp_path / "ex", detector=toy,
                   detector_meta={"detector_model": "toy.pt", "min_reflectance": f"{MIN_REFLECTANCE:g}"})
    sess = ort.InferenceSession(paths["detector"], providers=["CPUExecutionProvider"])
    cube = R.T.reshape(1, 4, -1, 1).numpy()
    mask, score = sess.run(None, {"cube": cube, "config": X[:1].numpy()})
    assert mask.shape == (1, len(R), 1)
    assert np.array_equal(mask.reshape(-1), toy.decide(R, X).numpy())
    assert 0 < int(mask.sum()) < len(R)
    cards = write_model_cards(tmp_path / "ex", {"method": "boxes"}, None,
                              {"detector": {"method": "ndsi_threshold", "pfa_budget": 1e-3}})
    text = Path(cards["detector_card"]).read_text()
    assert "`ndsi_threshold` detector kind" in text and "Made from `toy.pt`" in text
    # the exported graph judged by evaluate (as an onboard detector) gives the checkpoint's figures
    r2 = evaluate(tiny_dataset, [paths["detector"]])
    a, b = r["models"][0]["overall"], r2["models"][0]["overall"]
    for k in ("pd", "pd_sunlit", "pd_shadow", "pfa_scene", "pfa", "area_mean"):
        assert b[k] == pytest.approx(a[k], abs=1e-12), k


@pytest.mark.slow
def test_train_by_method_is_the_commands(tiny_dataset, tmp_path, capsys):
    """``registry.train`` (what ``torchskin train`` dispatches to) gives the model and summary the command writes."""
    from torchskin.cli import main

    assert main(["train", "--data", str(tiny_dataset), "--out", str(tmp_path / "c.pt"), "--method", "classifier",
                 "--steps", "3", "--hidden", "4"]) == 0
    text = capsys.readouterr().out
    model, info, line = registry.train(TrainRequest(tiny_dataset, "classifier", steps=3, hidden=4))
    ck = torch.load(tmp_path / "c.pt", map_location="cpu", weights_only=True)
    assert ck["kind"] == "classifier" and registry.kind_of(model) == "classifier"
    assert all(torch.equal(ck["state_dict"][k], v) for k, v in model.state_dict().items())
    assert {k: v for k, v in ck["meta"].items() if k not in ("training_manifest_sha256", "data", "surface", "light_model")} == info
    assert text.startswith(line)
    with pytest.raises(ValueError, match="unknown training method 'svm'"):
        registry.train(TrainRequest(tiny_dataset, "svm"))
