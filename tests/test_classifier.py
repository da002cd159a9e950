"""The configuration-conditioned classifier: scale-invariant inputs, a threshold that holds the false-alarm
budget on the earthlib train spectra, a checkpoint round trip, and detector.onnx equal to the torch model."""

import numpy as np
import pytest
import torch

from torchskin.detectors import classifier as Cl
from torchskin.detectors.features import tuning_configs

pytestmark = pytest.mark.slow  # the module fixture trains the classifier


def synthetic(n=3000, seed=0, shadowed=600):
    """Skin-like spectra (a rendered-skin shape at random brightness, plus a flat offset on some), the first
    ``shadowed`` of them again as skin in deep shadow (labelled skin, not sunlit: 1 % of the sunlit signal
    under sensor noise of 0.003 reflectance, so their indices are mostly ratios of noise), and non-skin rows
    (earthlib train spectra at random brightness), with random configurations."""
    g = torch.Generator().manual_seed(seed)
    X = torch.stack([torch.rand(n, generator=g) * 80, torch.rand(n, generator=g) * 70,
                     torch.rand(n, generator=g) * 180], -1)
    skin = torch.tensor([0.30, 0.60, 0.53, 0.08]) * (0.9 + 0.2 * torch.rand(n, 4, generator=g))
    skin = skin * (0.3 + 1.5 * torch.rand(n, 1, generator=g)) + 0.1 * torch.rand(n, 1, generator=g)
    C = Cl._earthlib_reflectance("train")
    neg = C[torch.randint(len(C), (n,), generator=g)] * (0.3 + 1.5 * torch.rand(n, 1, generator=g))
    shade = 0.01 * skin[:shadowed] + 0.003 * torch.randn(shadowed, 4, generator=g)
    label = torch.cat([torch.ones(n + shadowed, dtype=torch.bool), torch.zeros(n, dtype=torch.bool)])
    sunlit = torch.cat([torch.ones(n, dtype=torch.bool), torch.zeros(shadowed, dtype=torch.bool),
                        torch.ones(n, dtype=torch.bool)])
    return torch.cat([X, X[:shadowed], X]), torch.cat([skin, shade, neg]), label, sunlit


@pytest.fixture(scope="module")
def trained():
    X, R, label, sunlit = synthetic()
    model, info = Cl.train_classifier(X, R, label, sunlit, hidden=8, steps=300, batch=2048, max_tuning_configs=50,
                                      sunlit_only=True, scene_budget=None)
    return X, R, label & sunlit, model, info  # the sunlit skin: what the classifier is trained and scored on


def test_classifier_holds_the_scene_budget_on_its_training_non_skin():
    """With scene_budget, the threshold also keeps the training non-skin pixels called skin within the budget (and
    never lowers the earthlib threshold)."""
    X, R, label, sunlit = synthetic()
    free, fi = Cl.train_classifier(X, R, label, sunlit, hidden=8, steps=150, batch=2048, max_tuning_configs=50,
                                   sunlit_only=True, scene_budget=None)
    held, hi = Cl.train_classifier(X, R, label, sunlit, hidden=8, steps=150, batch=2048, max_tuning_configs=50,
                                   sunlit_only=True, scene_budget=0.0)
    assert hi["threshold"] >= fi["threshold"] and hi["scene_budget"] == 0.0
    with torch.no_grad():
        assert float(held.decide(R[~label], X[~label]).float().mean()) == 0.0
    with pytest.raises(ValueError, match="scene_budget"):
        Cl.train_classifier(X, R, label, sunlit, hidden=8, steps=1, scene_budget=1.5)


def test_ratio_features_are_scale_invariant_and_safe():
    R = torch.tensor([[0.3, 0.6, 0.5, 0.1], [0.0, 0.0, 0.5, 0.1], [0.0, 0.0, 0.0, 0.0]])
    f = Cl.ratio_features(R)
    torch.testing.assert_close(Cl.ratio_features(R * 3.7), f)
    torch.testing.assert_close(f[0], torch.tensor([-1 / 3, 2 / 3, 0.3 / 1.5]))
    assert bool(torch.isfinite(f).all()) and float(f[2].abs().sum()) == 0.0


def test_classifier_separates_and_holds_the_budget(trained):
    X, R, lit, model, info = trained
    keep = model.decide(R, X)
    skin = torch.arange(len(lit)) < 3600  # synthetic(): 3000 sunlit skin, 600 shadowed skin, 3000 non-skin
    assert int(lit.sum()) == 3000 and info["rows"] == 3000  # the positives: sunlit skin only
    assert float(keep[lit].float().mean()) > 0.9 and float(keep[~skin].float().mean()) < 0.01
    # the reported coverage is the fraction of the sunlit skin rows kept (one row: 1/3000), not of all skin
    # rows (the shadowed ones, never positives, are mostly rejected: the two differ by far more than a row)
    assert abs(info["train_coverage"] - float(keep[lit].float().mean())) < 0.5 / 3000
    assert abs(float(keep[skin].float().mean()) - float(keep[lit].float().mean())) > 10 / 3000
    # the tuned threshold: at most budget x m of the train spectra pass in any tuning configuration
    C = Cl._earthlib_reflectance("train")
    cfg = tuning_configs(model, X[:1])[1:][::37]  # a subset of the lattice the threshold was set on
    m = C.shape[0]
    hits = model.decide(C.repeat(len(cfg), 1), cfg.repeat_interleave(m, 0)).reshape(len(cfg), m).sum(1)
    assert int(hits.max()) <= int(np.floor(1e-3 * m)), hits.max()
    assert float(model.threshold) == info["threshold"] >= 0.0
    # the same scale-invariant decision at any brightness (the configuration and ratios are all it sees)
    assert bool((model.decide(R * 2.5, X) == keep).all())
    assert not bool(model.decide(torch.zeros(2, 4), X[:2]).any())


def test_checkpoint_round_trip_and_onnx_detector(trained, tmp_path):
    from torchskin.detectors.classifier import ClassifierDetector
    from torchskin.export import detector_graph, metadata, write_graphs
    from torchskin.onboard import OnboardDetector

    X, R, _, model, info = trained
    Cl.save(model, tmp_path / "c.pt", info)
    again = Cl.load(tmp_path / "c.pt")
    assert bool((again.decide(R, X) == model.decide(R, X)).all())
    with pytest.raises(ValueError, match="not a classifier"):
        from torchskin.detectors.boxes import BoxModel, save

        save(BoxModel(), tmp_path / "b.pt")
        Cl.load(tmp_path / "b.pt")
    paths = write_graphs({"detector": detector_graph(model, metadata(model))}, tmp_path)
    rng = np.random.default_rng(0)
    cube = (rng.random((2, 4, 24, 30)) * 0.7).astype(np.float32)
    cube[:, :, 5:15, 5:15] = np.array([0.3, 0.6, 0.53, 0.08], dtype=np.float32)[:, None, None]
    cfg = X[:2].numpy()
    out = OnboardDetector(paths["detector"], tile=1024)(cube, cfg, min_reflectance=0.0)
    with torch.no_grad():
        mt, st = ClassifierDetector(model)(torch.from_numpy(cube), torch.from_numpy(cfg))
    assert np.abs(out["score"] - st.numpy()).max() < 1e-4
    differ = out["mask"] != mt.numpy()
    assert (np.abs(st.numpy()[differ]) < 1e-4).all() and out["mask"][:, 5:15, 5:15].all()
    flat = torch.from_numpy(cube).permute(0, 2, 3, 1).reshape(-1, 4)
    cfgs = torch.from_numpy(cfg).repeat_interleave(24 * 30, 0)
    assert bool((model.decide(flat, cfgs).reshape(2, 24, 30).numpy() == mt.numpy()).all())
