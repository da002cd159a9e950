"""A detector kind is a module and a registration (issue 39, part 3): a kind registered from this test module,
with one training option of its own, goes through ``torchskin train`` -> ``evaluate`` -> ``export`` -> ``detect`` on
the command line, its option a ``train`` flag, with no edit outside this module."""

from __future__ import annotations

import json
from typing import Any, ClassVar

import numpy as np
import pytest
import torch
from torch import nn

from torchskin.detectors import registry
from torchskin.detectors.features import FEATURES, MIN_REFLECTANCE, config_buffers, domain_from_manifest
from torchskin.detectors.graphs import torch_detector_graph
from torchskin.detectors.protocol import KindOption, TrainRequest


def ndsi_score(n: torch.Tensor, s: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Positive where NDSI = (n - s) / (n + s) is above ``t``, without a division: n (1 - t) - s (1 + t)."""
    return n * (1 - t) - s * (1 + t)


class ThresholdGraph(nn.Module):
    """What the kind's ``detector.onnx`` computes: (cube (B, 4, H, W), config) -> (mask, score)."""

    def __init__(self, t: torch.Tensor):
        super().__init__()
        self.t = t

    def forward(self, cube: torch.Tensor, config: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        score = ndsi_score(cube[:, 2], cube[:, 3], self.t)
        return score > 0, score


class ThresholdKind(nn.Module):
    """A test kind: skin where NDSI is above the ``--quantile`` quantile of the training skin's NDSI."""

    kind: ClassVar[str] = "ndsi_quantile"
    methods: ClassVar[tuple[str, ...]] = ("ndsi_quantile",)
    options: ClassVar[tuple[KindOption, ...]] = (
        KindOption("quantile", 0.05, "ndsi_quantile: the quantile of the training skin's NDSI that is the threshold "
                                     "(default 0.05)"),)
    method_help: ClassVar[str] = "ndsi_quantile: NDSI above a quantile of the training skin's (a test kind)"
    card_use: ClassVar[str] = "Skin where NDSI is above a learned threshold (a test kind)."
    threshold: torch.Tensor
    domain: torch.Tensor

    def __init__(self, threshold: float = 0.5, features: Any = FEATURES, domain: Any = None):
        super().__init__()
        self.features = tuple(features)
        self.register_buffer("threshold", torch.tensor(float(threshold)))
        self.register_buffer("domain", config_buffers(self.features, domain=domain)[2])

    def decide(self, R: torch.Tensor, config: torch.Tensor) -> torch.Tensor:
        R = torch.as_tensor(R, dtype=torch.float32)
        return ndsi_score(R[:, 2], R[:, 3], self.threshold) > 0

    def detector_graph(self, meta: dict[str, str]) -> Any:
        return torch_detector_graph(ThresholdGraph(self.threshold), len(self.features), meta)

    def checkpoint(self, meta: dict) -> dict:
        return {"state_dict": self.state_dict(), "features": list(self.features), "meta": meta}

    @classmethod
    def from_checkpoint(cls, ck: dict) -> ThresholdKind:
        m = cls(features=ck["features"])
        m.load_state_dict(ck["state_dict"])
        return m.eval()

    @classmethod
    def from_training(cls, req: TrainRequest) -> tuple[ThresholdKind, dict, str]:
        from torchskin.detectors.classifier import load_rows

        q = float(req.options["quantile"])
        X, R, label, sunlit = load_rows(req.data, frames=req.frames)
        skin = R[label & sunlit]
        ndsi = (skin[:, 2] - skin[:, 3]) / (skin[:, 2] + skin[:, 3])
        t = float(np.quantile(ndsi, q))
        model = cls(t, domain=domain_from_manifest(req.data)).eval()
        info = {"method": req.method, "rows": int(len(skin)), "threshold": t, "pfa_budget": req.pfa_budget,
                "options": {"quantile": q}, "light_classes": ["sunlit"]}
        return model, info, f"trained ({req.method}) on {len(skin)} sunlit skin pixels; NDSI threshold {t:.3f}"


@pytest.fixture
def threshold_kind():
    registry.register(ThresholdKind)
    try:
        yield ThresholdKind
    finally:
        registry.unregister(ThresholdKind.kind)


def test_a_kind_registered_here_is_on_the_command_line(threshold_kind, tiny_dataset, tmp_path, capsys):
    """train (with the kind's own ``--quantile`` flag) -> evaluate -> export -> detect, the detect mask the kind's
    own decisions on a frame of the dataset's rendered pixels."""
    from torchskin.cli import main
    from torchskin.cubefiles import read_png_gray
    from torchskin.dataset.files import read_valid

    ds, pt = str(tiny_dataset), str(tmp_path / "thr.pt")
    # the kind's option is a train flag, in its --help, and refused with another kind's --method (and back)
    assert main(["train", "--help"]) == 0
    assert "--quantile QUANTILE" in capsys.readouterr().out
    assert main(["train", "--data", ds, "--out", pt, "--method", "boxes", "--quantile", "0.2"]) == 2
    assert "--quantile is an option of --method ndsi_quantile" in capsys.readouterr().err
    assert main(["train", "--data", ds, "--out", pt, "--method", "ndsi_quantile", "--margin", "0.1"]) == 2
    assert "--margin is an option of --method boxes|quantiles" in capsys.readouterr().err
    # train
    assert main(["train", "--data", ds, "--out", pt, "--method", "ndsi_quantile", "--quantile", "0.2",
                 "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["options"] == {"quantile": 0.2} and info["method"] == "ndsi_quantile"
    model, ck = registry.load(pt)
    assert isinstance(model, ThresholdKind) and ck["kind"] == "ndsi_quantile"
    assert float(model.threshold) == pytest.approx(info["threshold"])
    # evaluate: judged by its own decisions
    t, _ = read_valid(tiny_dataset, ["r544", "r633", "r1080", "r1580", "label", "shadow", *FEATURES])
    col = {c: t.column(c).to_numpy(zero_copy_only=False) for c in t.column_names}
    R = torch.from_numpy(np.stack([col[c] for c in ("r544", "r633", "r1080", "r1580")], -1).astype(np.float32))
    X = torch.from_numpy(np.stack([col[f] for f in FEATURES], -1).astype(np.float32))
    lit = torch.from_numpy(col["label"] & ~col["shadow"])
    assert main(["evaluate", "--data", ds, "--model", pt, "--json"]) == 0
    ev = json.loads(capsys.readouterr().out)
    assert [m["kind"] for m in ev["models"]] == ["ndsi_quantile", "static"]
    hit = model.decide(R, X) & (R.mean(-1) > MIN_REFLECTANCE)
    assert ev["models"][0]["overall"]["pd_sunlit"] == pytest.approx(float(hit[lit].float().mean()), abs=1e-12)
    # export: a kind without boxes is detector.onnx alone, with its card
    out = tmp_path / "ex"
    assert main(["export", "--model", pt, "--out", str(out), "--json"]) == 0
    paths = json.loads(capsys.readouterr().out)
    assert set(paths) == {"detector", "detector_card"} and not (out / "boundaries.onnx").exists()
    import onnx

    meta = {p.key: p.value for p in onnx.load(paths["detector"]).metadata_props}
    assert meta["kind"] == "ndsi_quantile" and meta["detector_reason"] == "the ndsi_quantile model of --model"
    card = (out / "detector.md").read_text()
    assert "Skin where NDSI is above a learned threshold" in card and "`ndsi_quantile`" in card
    # detect on a frame of rendered pixels (one configuration, the kind ignores it): the kind's own decisions
    ok = ((R >= 0) & (R <= 1)).all(-1)
    Rf = R[ok][: 24 * 8]
    assert len(Rf) == 24 * 8
    cube = Rf.T.reshape(4, 24, 8).numpy()
    np.save(tmp_path / "frame.npy", cube)
    x0 = X[0].tolist()
    assert main(["detect", "--model", paths["detector"], "--cube", str(tmp_path / "frame.npy"),
                 "--sun-zenith", f"{x0[0]}", "--camera-zenith", f"{x0[1]}", "--relative-azimuth", f"{x0[2]}",
                 "--out", str(tmp_path / "mask.png"), "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    mask = read_png_gray(tmp_path / "mask.png") > 0
    want = (model.decide(Rf, X[:1].expand(len(Rf), -1)) & (Rf.mean(-1) > MIN_REFLECTANCE)).reshape(24, 8).numpy()
    assert mask.shape == (24, 8) and np.array_equal(mask, want)
    assert res["skin_pixels"] == int(want.sum()) and 0 < int(want.sum()) < want.size  # the test can tell


def test_the_kind_leaves_no_trace(capsys):
    """Unregistered, the kind is gone from the registry and from the command line."""
    from torchskin.cli import main

    assert ThresholdKind.kind not in registry.kinds() and "--quantile" not in registry.option_kinds()
    assert main(["train", "--help"]) == 0
    help_text = capsys.readouterr().out
    assert "--quantile" not in help_text and "ndsi_quantile" not in help_text and "--margin" in help_text


def test_what_the_builtin_kinds_contribute():
    """The built-in kinds' options, heads and onboard choice, read through the registry; the onboard runtime's box
    head serves exactly the kinds that ask for it."""
    from torchskin.evaluation import ONBOARD_KINDS
    from torchskin.onboard import BOX_HEAD_KINDS

    assert [o.cli_flag for o in registry.options(registry.get("boxes"))] == [
        "--margin", "--width-cost", "--spread-cost", "--q", "--no-ndvn-rule"]
    assert registry.options(registry.get("classifier")) == ()
    assert {k for k in registry.kinds() if registry.onboard_head(k) == "boxes"} == BOX_HEAD_KINDS
    assert registry.onboard_kinds() == ONBOARD_KINDS == ("boxes", "lut")
    assert registry.box_kinds() == ("boxes",)


def test_register_refuses_a_taken_or_common_flag():
    class Clash(ThresholdKind):
        kind, methods = "clash", ("clash",)
        options = (KindOption("margin", 0.1, "taken"),)

    class Common(ThresholdKind):
        kind, methods = "common", ("common",)
        options = (KindOption("steps", 3, "the command's own", int),)

    with pytest.raises(ValueError, match="--margin of kind 'clash' already belong to boxes"):
        registry.register(Clash)
    with pytest.raises(ValueError, match="not torchskin train's own"):
        registry.register(Common)
    assert "clash" not in registry.kinds() and "common" not in registry.kinds()
    with pytest.raises(ValueError, match="has no option"):
        registry.train(TrainRequest("nowhere", "classifier", options={"margin": 0.1}))


def test_a_kind_names_its_onboard_head_where_its_name_does_not(threshold_kind):
    """The built-in kinds' graphs record no ``onboard_head`` (their names tell it); a new kind's records the head
    it asks for when that is not the generic one, and the onboard runtime reads it."""
    from torchskin.export import metadata
    from torchskin.onboard import detector_head

    class BoxHeaded(ThresholdKind):
        kind, methods, onboard_head, options = "box_headed", ("box_headed",), "boxes", ()

    assert "onboard_head" not in metadata(ThresholdKind()) and "onboard_head" not in metadata(registry.get("boxes")())
    registry.register(BoxHeaded)
    try:
        assert metadata(BoxHeaded())["onboard_head"] == "boxes"
    finally:
        registry.unregister("box_headed")
    assert detector_head({"kind": "ndsi_quantile"}, "unused.onnx", None) == ("generic", None)
    with pytest.raises(ValueError, match="onboard_head must be one of"):
        registry.register(type("Bad", (ThresholdKind,), {"kind": "bad", "methods": ("bad",), "onboard_head": "gpu"}))
