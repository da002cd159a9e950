"""A configuration-conditioned skin classifier: a small MLP on scale-invariant band ratios of the ELM
reflectance and the configuration, the comparison the learned boxes must beat (``torchskin evaluate``).

Inputs per pixel: three normalised differences of the four bands (g, r, n, s) = (544, 633, 1080, 1580) nm,

    NDGRI = (g - r) / (g + r),   NDSI = (n - s) / (n + s),   NDVN = ((g + r) - (n + s)) / (g + r + n + s),

which describe the spectrum up to its overall scale (the "indices plus brightness" of the issue, with the
brightness taken as the visible / NIR ratio rather than an absolute level: ELM reflectance of a surface that
is not parallel to the panels is its reflectance times a geometric factor of 0 to ~1/cos(sun zenith), so an
absolute brightness would let a bright confuser look like skin, and earthlib's test spectra could not show
it). NDVN carries what boxes on (NDGRI, NDSI) cannot see: a glint adds the same reflectance to every band, so
it drives NDSI towards 0 while the visible/NIR balance of skin stays far from that of soils and vegetation.
The configuration features (sun zenith, camera zenith, relative azimuth) are standardised and concatenated.

The logit is a linear function of those inputs plus a small MLP of them: logit = a·x + b + MLP(x). Training
(``train_classifier``) starts from the data, not from the seed: (a, b) is first fitted alone, a convex weighted
logistic regression on every training row and every earthlib train spectrum under a fixed lattice of
configurations (one optimum whatever the seed), with the MLP's output layer at zero; Adam then refines all of it on
the weighted logistic loss; positives are the sunlit skin pixels of a
generated dataset (every configuration weighing the same), negatives the scene's non-skin pixels (clothing,
ground, confusers of the training partition) and every earthlib *train* spectrum under random configurations
over the training domain. The decision threshold is then raised until at most ``pfa_budget`` of the earthlib
train spectra are called skin in any configuration of the tuning set (``tune_threshold``: the boxes' rule).

This module is the ``classifier`` detector kind (``torchskin.detectors.registry``); ``SkinClassifier`` is its model.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, fields, replace
from typing import TYPE_CHECKING, Any, ClassVar, cast

import numpy as np
import torch
from torch import nn

from ..bands import INDEX_BANDS_NM
from .features import (
    BAND_COLUMNS,
    FEATURES,
    config_buffers,
    distinct_configs,
    domain_from_manifest,
    earthlib_reflectance,
    ratio_indices,
    tuning_configs,
)
from .graphs import torch_detector_graph
from .protocol import PipelineRun, write_checkpoint

if TYPE_CHECKING:
    import onnx

    from .protocol import CalibrationData, TrainRequest


def ratio_features(R: torch.Tensor) -> torch.Tensor:
    """The classifier's per-pixel inputs: (NDGRI, NDSI, NDVN) (``detect.ratio_indices``) of reflectance
    (..., 4) -> (..., 3), 0 where a band sum is not positive (such pixels are never skin: see
    ``SkinClassifier.decide``).

    >>> ratio_features(torch.tensor([[0.3, 0.6, 0.5, 0.1], [0.0, 0.0, 0.5, 0.1]])).round(decimals=4)
    tensor([[-0.3333,  0.6667,  0.2000],
            [ 0.0000,  0.6667, -1.0000]])
    """
    return torch.stack(ratio_indices(R, zero_undefined=True), -1)


class SkinClassifier(nn.Module):
    """Configuration features (N, k) and reflectance (N, 4) -> skin logit (N,): ``linear(x) + net(x)`` of the
    inputs x = (2 x ratio features, standardised configuration) (``inputs``).

    The ``classifier`` detector kind (``protocol.DetectorModel``): ``decide`` thresholds the logit,
    ``detector_graph`` is its ONNX export (``ClassifierDetector``), ``checkpoint`` / ``from_checkpoint`` its torch
    checkpoint (``save`` / ``load``)."""

    kind: ClassVar[str] = "classifier"
    #: the training methods of this kind (``train_classifier``)
    methods: ClassVar[tuple[str, ...]] = ("classifier",)
    #: the band centres (nm) its training and evaluation data must hold (``registry.required_bands``): the four
    #: index bands, whose columns (``BAND_COLUMNS``) it reads
    required_bands: ClassVar[tuple[float, ...]] = INDEX_BANDS_NM
    #: its method in ``torchskin train --method``'s help (its options are the command's common ones: --hidden,
    #: --steps, --seed)
    method_help: ClassVar[str] = ("classifier: a configuration-conditioned MLP on scale-invariant band ratios "
                                  "(torchskin.detectors.classifier), thresholded at the false-alarm budget")
    #: the onboard runtime runs its graph as it is (``onboard.detector_head``); its per-pixel MLP (3 -> 32 -> 32 ->
    #: 1) takes ~170 ms per 1024² frame, 40x the box graph: evaluated and reported, not shipped as detector.onnx
    onboard_head: ClassVar[str] = "generic"
    onboard_selectable: ClassVar[bool] = False
    onboard_cost: ClassVar[str] = "a per-pixel MLP, ~40x the box graph's time per frame"
    #: the model card's words for its ``detector.onnx`` score
    card_score: ClassVar[str] = "the classifier: its logit minus the calibrated threshold"
    #: ``make demo`` trains, calibrates and compares one classifier
    pipeline_runs: ClassVar[tuple[PipelineRun, ...]] = (PipelineRun("classifier", ("--method", "classifier")),)

    # buffers (declared for type checkers; ``register_buffer`` creates them)
    mean: torch.Tensor
    std: torch.Tensor
    threshold: torch.Tensor
    domain: torch.Tensor

    def __init__(self, features: Sequence[str] = FEATURES, hidden: int = 32, mean: Any = None, std: Any = None,
                 domain: Any = None):
        super().__init__()
        self.features = tuple(features)
        k = len(self.features)
        if hidden < 1:
            raise ValueError(f"hidden must be >= 1, got {hidden}")
        self.hidden = int(hidden)
        mean_t, std_t, domain_t = config_buffers(self.features, mean, std, domain)
        self.register_buffer("mean", mean_t)
        self.register_buffer("std", std_t)
        self.register_buffer("threshold", torch.zeros(()))  # logit above which a pixel is skin (``tune_threshold``)
        self.register_buffer("domain", domain_t)
        self.net = nn.Sequential(nn.Linear(3 + k, hidden), nn.Tanh(), nn.Linear(hidden, hidden), nn.Tanh(),
                                 nn.Linear(hidden, 1))
        self.linear = nn.Linear(3 + k, 1)  # the convex part (``fit_linear``): the MLP refines it

    def inputs(self, R: torch.Tensor, config: torch.Tensor) -> torch.Tensor:
        """The per-pixel inputs (N, 3 + k): twice the ratio features, then the standardised configuration."""
        return torch.cat([ratio_features(R) * 2.0, (config - self.mean) / self.std], -1)

    def forward(self, R: torch.Tensor, config: torch.Tensor) -> torch.Tensor:
        x = self.inputs(R, config)
        return (self.net(x) + self.linear(x)).squeeze(-1)

    @torch.no_grad()
    def decide(self, R: torch.Tensor, config: torch.Tensor, chunk: int = 1 << 18) -> torch.Tensor:
        """Skin mask (N,) of reflectance (N, 4) under configurations (N, k), in chunks (no graph)."""
        R = torch.as_tensor(R, dtype=torch.float32)
        config = torch.as_tensor(config, dtype=torch.float32)
        out = torch.empty(R.shape[0], dtype=torch.bool)
        for lo in range(0, R.shape[0], chunk):
            r = R[lo:lo + chunk]
            ok = (r[:, :2].sum(-1) > 0) & (r[:, 2:].sum(-1) > 0)
            out[lo:lo + chunk] = ok & (self(r, config[lo:lo + chunk]) > self.threshold)
        return out

    # --------------------------------------------------------------------- the detector kind (protocol.DetectorModel)
    def detector_graph(self, meta: dict[str, str]) -> onnx.ModelProto:
        """``detector.onnx`` of the classifier (``ClassifierDetector``), with metadata ``meta``."""
        return torch_detector_graph(ClassifierDetector(self.eval()), len(self.features), meta)

    def reference_detector(self) -> nn.Module:
        """The torch module ``detector.onnx`` computes (``ClassifierDetector``)."""
        return ClassifierDetector(self)

    def checkpoint(self, meta: dict) -> dict:
        """State, features, hidden size and metadata (``registry.save`` adds the kind)."""
        return {"state_dict": self.state_dict(), "features": list(self.features), "hidden": self.hidden,
                "meta": meta}

    @classmethod
    def from_checkpoint(cls, ck: dict) -> SkinClassifier:
        """The classifier of a checkpoint dict (those written before the linear part get a zero one), in eval
        mode; ``ValueError`` for a checkpoint of another kind."""
        if ck.get("kind") != "classifier":
            raise ValueError("not a classifier checkpoint")
        m = cls(ck["features"], ck["hidden"])
        state = dict(ck["state_dict"])
        state.setdefault("linear.weight", torch.zeros_like(m.linear.weight))  # written before the linear part: none
        state.setdefault("linear.bias", torch.zeros_like(m.linear.bias))
        m.load_state_dict(state)
        return m.eval()

    @classmethod
    def from_training(cls, req: TrainRequest) -> tuple[SkinClassifier, dict, str]:
        """``torchskin train --method classifier``: the model, its training summary and the one-line report
        (``train_on_dataset``)."""
        return train_on_dataset(req)

    def calibrate_to_budget(self, data: CalibrationData, scene_budget: float, pfa_budget: float,
                            iters: int = 30) -> dict:
        """``evaluation.calibrate_to_budget`` for the classifier: the lowest logit threshold, never below the current
        one, at which at most ``scene_budget`` of the non-skin rows (the bright ones can pass) are called skin. Sets
        it and returns knob, before, after and pfa_scene."""
        nonskin, bright = data.nonskin, data.bright
        with torch.no_grad():
            logit = self(data.R[nonskin & bright], data.X[nonskin & bright])
        k = int(math.floor(scene_budget * int(nonskin.sum())))
        before = float(self.threshold)
        need = float(logit.sort(descending=True).values[k]) if k < logit.numel() else before
        self.threshold.fill_(max(before, need))
        with torch.no_grad():
            rate = float((self.decide(data.R[nonskin], data.X[nonskin]) & bright[nonskin]).float().mean())
        return {"knob": "threshold", "before": before, "after": float(self.threshold), "pfa_scene": rate}

    #: the model card's "Intended use" of this kind (``modelcard``)
    card_use: ClassVar[str] = (
        "Onboard skin detection in 4-band (544, 633, 1080, 1580 nm) reflectance imagery with a "
        "configuration-conditioned MLP on the band ratios NDGRI, NDSI and NDVN (`torchskin.detectors.classifier`), "
        "thresholded at the false-alarm budget.")

    @staticmethod
    def card_false_alarms(train: dict, f: Any) -> str:
        """The model card's account of the threshold tuning (``tune_threshold``) from the training summary
        ``train``, numbers formatted with ``f``."""
        return (f"the decision threshold was raised to {f(train.get('threshold'))} (logit) so that at most "
                f"{f(train.get('pfa_budget'))} of the earthlib *train* spectra are called skin in any of "
                f"{train.get('calibration_configs', 'n/a')} configurations")


class ClassifierDetector(nn.Module):
    """``detector.onnx`` for a ``SkinClassifier``: cube (B, 4, H, W) + configuration (B, k) -> mask and score
    (B, H, W), score = logit - threshold (positive: skin). The configuration's part of the first layer (and of the
    linear part) is computed once per frame; per pixel the three band ratios go through the MLP and the linear
    part."""

    def __init__(self, classifier: SkinClassifier):
        super().__init__()
        self.c = classifier

    def forward(self, cube: torch.Tensor, config: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Mask and score (B, H, W) of a reflectance cube (B, 4, H, W) under configurations (B, k)."""
        B, _, H, W = cube.shape
        x = cube.reshape(B, 4, H * W).transpose(1, 2)  # (B, HW, 4)
        first, *rest = list(self.c.net)
        first = cast(nn.Linear, first)
        w = first.weight
        cfg = (config - self.c.mean) / self.c.std  # (B, k)
        bias = cfg @ w[:, 3:].T + first.bias  # (B, hidden): the configuration's part, once per frame
        feats = ratio_features(x) * 2.0
        h = feats @ w[:, :3].T + bias[:, None, :]
        for layer in rest:
            h = layer(h)
        lw, lb = self.c.linear.weight[0], self.c.linear.bias  # the linear part, its configuration term per frame
        h = h.squeeze(-1) + feats @ lw[:3] + (cfg @ lw[3:] + lb)[:, None]
        valid = (x[..., 0] + x[..., 1] > 0) & (x[..., 2] + x[..., 3] > 0)
        score = (h - self.c.threshold).reshape(B, H, W)
        return (score > 0) & valid.reshape(B, H, W), score


def load_rows(data_dir: str | os.PathLike, features: Sequence[str] = FEATURES, frames: str = "physical"
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Training rows of a generated dataset (the frames ``frames`` names: ``dataset.files.read_rows``):
    configuration (n, k), reflectance (n, 4), skin label and sunlit flag (numpy)."""
    from ..dataset.files import read_rows

    rows = read_rows(data_dir, [*features, *BAND_COLUMNS, "label", "shadow"], frames)
    X = rows.stack(features, np.float32)
    R = rows.bands(np.float32)
    ok = np.isfinite(X).all(1) & np.isfinite(R).all(1)
    return X[ok], R[ok], rows["label"][ok].astype(bool), ~rows["shadow"][ok].astype(bool)


def _earthlib_reflectance(part: str) -> torch.Tensor:
    return earthlib_reflectance(part)


#: the configuration lattice (per feature) the earthlib spectra are placed under for the linear start
LINEAR_LATTICE = 5


def fit_linear(model: SkinClassifier, Rp: torch.Tensor, Xp: torch.Tensor, wp: torch.Tensor, Rn: torch.Tensor,
               Xn: torch.Tensor, C: torch.Tensor, confuser_weight: float, l2: float = 1e-4, iters: int = 100) -> float:
    """Set ``model.linear`` to the weighted logistic regression of the training loss's three parts on all their
    rows: positives ``Rp`` (configurations ``Xp``, weights ``wp`` summing to 1), negatives ``Rn`` (``Xn``) and the
    earthlib spectra ``C`` under a ``LINEAR_LATTICE``^k lattice over the model's domain (``confuser_weight``),
    with a small L2 penalty ``l2`` (finite weights on separable data). A convex problem solved by L-BFGS in
    float64: the same optimum for any seed, thread count or start. Returns the loss."""
    axes = [torch.linspace(float(lo), float(hi), LINEAR_LATTICE) for lo, hi in model.domain]
    lattice = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, len(axes))
    with torch.no_grad():
        xp, xn = model.inputs(Rp, Xp).double(), model.inputs(Rn, Xn).double()
        xc = model.inputs(C.repeat(len(lattice), 1), lattice.repeat_interleave(len(C), 0)).double()
    wp = wp.double()
    w = torch.zeros(xp.shape[1], dtype=torch.float64, requires_grad=True)
    b = torch.zeros((), dtype=torch.float64, requires_grad=True)
    opt = torch.optim.LBFGS([w, b], lr=1.0, max_iter=iters, tolerance_grad=1e-10, tolerance_change=1e-14,
                            history_size=20, line_search_fn="strong_wolfe")
    softplus = nn.functional.softplus

    def loss_fn() -> torch.Tensor:  # bce(z, 1) = softplus(-z), bce(z, 0) = softplus(z)
        return ((softplus(-(xp @ w + b)) * wp).sum() + softplus(xn @ w + b).mean()
                + confuser_weight * softplus(xc @ w + b).mean() + l2 * w.square().sum())

    def closure() -> torch.Tensor:
        opt.zero_grad()
        loss = loss_fn()
        loss.backward()
        return loss

    opt.step(closure)
    with torch.no_grad():
        model.linear.weight.copy_(w[None].float())
        model.linear.bias.copy_(b.reshape(1).float())
        return float(loss_fn())


@dataclass(frozen=True)
class ClassifierTraining:
    """The settings of ``train_classifier`` (see there for what each does).

    Attributes:
        features: the names of the columns of ``X``.
        hidden, steps, lr, batch, seed: network width, Adam steps (cosine-decayed rate), batch size, seed.
        domain: the training domain per feature (None: the extremes of ``X``).
        pfa_budget: the largest fraction of the earthlib train spectra called skin in any tuning configuration.
        confuser_weight: the weight of the earthlib spectra in the loss.
        max_tuning_configs: at most this many training configurations (plus the domain lattice) for the threshold.
        scene_budget: the largest share of the training non-skin pixels called skin (None: not held).
        sunlit_only: positives are the sunlit skin pixels only.
    """

    features: Sequence[str] = FEATURES
    hidden: int = 32
    steps: int = 1500
    lr: float = 3e-3
    batch: int = 16384
    seed: int = 0
    domain: Any = None
    pfa_budget: float = 1e-3
    confuser_weight: float = 4.0
    max_tuning_configs: int = 2000
    scene_budget: float | None = 1e-4
    sunlit_only: bool = False

    def with_options(self, **options: Any) -> ClassifierTraining:
        """A copy with ``options`` (field names) changed; ``TypeError`` naming an unknown one."""
        unknown = sorted(set(options) - {f.name for f in fields(self)})
        if unknown:
            raise TypeError(f"train_classifier got unexpected option(s) {', '.join(unknown)}")
        return replace(self, **options)


def train_classifier(X: Any, R: Any, label: Any, sunlit: Any, settings: ClassifierTraining | None = None,
                     **options: Any) -> tuple[SkinClassifier, dict]:
    """Fit a ``SkinClassifier`` (see the module docstring) on skin pixels (sunlit and shadowed; ``sunlit_only``:
    sunlit) against the dataset's non-skin pixels and the earthlib train partition, then tune its threshold to
    ``pfa_budget`` on the earthlib train partition (``tune_threshold``) and, with ``scene_budget``, so that at
    most that share of the training non-skin pixels is called skin. Deterministic in ``seed``.

    Args:
        X, R, label, sunlit: configuration features, ELM reflectance (``BAND_COLUMNS`` order), skin label and
            sunlit flag per pixel (``load_rows``; numpy arrays or tensors).
        features: the names of the columns of ``X``.
        hidden, steps, lr, batch, seed: network width, Adam steps (cosine-decayed rate), batch size, seed.
        domain: the training domain per feature (default: the extremes of ``X``).
        pfa_budget: the largest fraction of the earthlib train spectra called skin in any tuning configuration.
        confuser_weight: the weight of the earthlib spectra (random configurations) in the loss.
        max_tuning_configs: at most this many training configurations (plus the domain lattice) for the
            threshold.

    Shape:
        X: (n, k); R: (n, 4); label, sunlit: (n,); domain: (k, 2).

    Returns:
        The model (eval mode) and a summary: method, rows, loss, threshold, pfa_budget, train_coverage,
        pfa_scene_train, calibration_configs (the number of tuning configurations), options.

    The settings are a ``ClassifierTraining`` (default: its defaults); keyword ``options`` (its field names, e.g.
    ``hidden=8, steps=300``) change single fields.
    """
    st = (settings or ClassifierTraining()).with_options(**options)
    features, hidden, steps, lr, batch, seed = st.features, st.hidden, st.steps, st.lr, st.batch, st.seed
    domain, pfa_budget, confuser_weight = st.domain, st.pfa_budget, st.confuser_weight
    max_tuning_configs, scene_budget, sunlit_only = st.max_tuning_configs, st.scene_budget, st.sunlit_only
    X, R = torch.as_tensor(X), torch.as_tensor(R)
    label, sunlit = torch.as_tensor(label), torch.as_tensor(sunlit)
    pos = label & sunlit if sunlit_only else label.clone()
    neg = ~label
    if int(pos.sum()) < 10 or int(neg.sum()) < 10:
        raise ValueError(f"need at least 10 {'sunlit ' if sunlit_only else ''}skin and 10 non-skin pixels, got "
                         f"{int(pos.sum())} and {int(neg.sum())}")
    if scene_budget is not None and not (0.0 <= scene_budget < 1.0):
        raise ValueError(f"scene_budget must lie in [0, 1), got {scene_budget}")
    if not (0.0 <= pfa_budget < 1.0):
        raise ValueError(f"pfa_budget must lie in [0, 1), got {pfa_budget}")
    if steps < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    g = torch.Generator().manual_seed(seed)  # the network's own generator: torch's global one is left alone
    Xp, Rp = X[pos], R[pos]
    Xn, Rn = X[neg], R[neg]
    if domain is None:
        domain = torch.stack([X.min(0).values, X.max(0).values], -1)
    domain = torch.as_tensor(domain, dtype=torch.float32)
    with torch.random.fork_rng(devices=[]):  # nn.Linear's default initialisation draws from the global generator
        model = SkinClassifier(features, hidden, X.mean(0), X.std(0).clamp_min(1e-6), domain)
    with torch.no_grad():  # the MLP's weights from the seed (uniform +-1/sqrt(fan-in), as nn.Linear's default), its
        layers = [m for m in model.net if isinstance(m, nn.Linear)]  # output layer at zero: it starts as fit_linear's
        for layer in layers:
            for p in (layer.weight, layer.bias):
                p.copy_((torch.rand(p.shape, generator=g) * 2 - 1) / math.sqrt(layer.in_features))
        layers[-1].weight.zero_()
        layers[-1].bias.zero_()
    _, inv = distinct_configs(Xp)  # every configuration weighs the same among the positives
    cnt = torch.bincount(inv).float()
    wp = (1.0 / cnt[inv])
    wp = wp / wp.sum()
    C = _earthlib_reflectance("train")
    linear_loss = fit_linear(model, Rp, Xp, wp, Rn, Xn, C, confuser_weight)
    lo, hi = domain[:, 0], domain[:, 1]
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps, eta_min=lr * 0.01)
    bce = nn.functional.binary_cross_entropy_with_logits
    loss = torch.tensor(0.0)
    for _ in range(steps):
        ip = torch.multinomial(wp, batch, replacement=True, generator=g)
        i_n = torch.randint(len(Xn), (batch,), generator=g)
        ic = torch.randint(len(C), (batch,), generator=g)
        cfg_c = lo + (hi - lo) * torch.rand(batch, len(lo), generator=g)
        opt.zero_grad()
        lp = model(Rp[ip], Xp[ip])
        ln = model(Rn[i_n], Xn[i_n])
        lc = model(C[ic], cfg_c)
        loss = (bce(lp, torch.ones_like(lp)) + bce(ln, torch.zeros_like(ln))
                + confuser_weight * bce(lc, torch.zeros_like(lc)))
        loss.backward()
        opt.step()
        sched.step()
    model.eval()
    tuning = tuning_configs(model, Xp)
    if tuning.shape[0] > max_tuning_configs:  # the lattice (last) and a fixed subset of training configurations
        lattice = tuning_configs(model, Xp[:1])[1:]
        pick = torch.randperm(tuning.shape[0] - lattice.shape[0], generator=g)[:max_tuning_configs]
        tuning = torch.cat([tuning[pick], lattice])
    threshold = tune_threshold(model, tuning, C, pfa_budget)
    if scene_budget is not None:  # the training scene's non-skin pixels: the (k+1)-th highest logit must not pass
        with torch.no_grad():
            k = int(math.floor(scene_budget * len(Rn)))
            kth = float(model(Rn, Xn).sort(descending=True).values[min(k, len(Rn) - 1)])
        threshold = max(threshold, kth)
        model.threshold.fill_(threshold)
    with torch.no_grad():
        keep = model.decide(Rp, Xp)
        coverage = float(keep.float().mean())
        scene = float(model.decide(Rn, Xn).float().mean())
    return model, {"method": "classifier", "rows": int(pos.sum()), "loss": float(loss.detach()),
                   "threshold": threshold, "pfa_budget": pfa_budget, "train_coverage": coverage,
                   "scene_budget": scene_budget, "light_classes": ["sunlit"] if sunlit_only else ["sunlit", "shadow"],
                   # the key keeps its old name: checkpoints and model cards carry it
                   "pfa_scene_train": scene, "calibration_configs": int(tuning.shape[0]),
                   "linear_loss": linear_loss,
                   "options": {"hidden": hidden, "steps": steps, "lr": lr, "seed": seed,
                               "confuser_weight": confuser_weight}}


@torch.no_grad()
def tune_threshold(model: SkinClassifier, configs: torch.Tensor, spectra: torch.Tensor,
                   budget: float = 1e-3) -> float:
    """The smallest logit threshold (>= 0) at which at most ``budget`` of ``spectra`` (m, 4) are called skin in
    every configuration of ``configs``. Sets and returns ``model.threshold``."""
    m = spectra.shape[0]
    k = int(math.floor(budget * m))  # spectra allowed per configuration
    worst = torch.full((), -math.inf)
    per = max(1, (1 << 20) // m)
    for lo in range(0, configs.shape[0], per):
        c = configs[lo:lo + per]
        logit = model(spectra.repeat(c.shape[0], 1), c.repeat_interleave(m, 0)).reshape(c.shape[0], m)
        kth = logit.sort(dim=1, descending=True).values[:, k]  # the (k+1)-th highest logit: must not pass
        worst = torch.maximum(worst, kth.max())
    thr = max(0.0, float(worst))
    model.threshold.fill_(thr)
    return thr


def save(model: SkinClassifier, path: str | os.PathLike, meta: dict | None = None) -> None:
    """A torch checkpoint (kind "classifier"), written atomically; the same model gives the same bytes."""
    write_checkpoint(model, path, meta)


def load(path: str | os.PathLike) -> SkinClassifier:
    """A ``SkinClassifier`` from a checkpoint written by ``save`` (``ValueError`` for other checkpoints), in eval
    mode."""
    ck = torch.load(path, map_location="cpu", weights_only=True)
    if ck.get("kind") != "classifier":
        raise ValueError(f"{str(path)!r} is not a classifier checkpoint")
    return SkinClassifier.from_checkpoint(ck)


def train_on_dataset(req: TrainRequest) -> tuple[SkinClassifier, dict, str]:
    """``torchskin train --method classifier`` on a dataset folder: the rows (``load_rows``), the declared domain
    (``domain_from_manifest``), ``train_classifier`` with the request's options (width at least 1); returns the
    model, its training summary and the command's one-line report."""
    X, R, label, sunlit = load_rows(req.data, frames=req.frames)
    model, info = train_classifier(X, R, label, sunlit, hidden=max(req.hidden, 1), steps=req.steps, seed=req.seed,
                                   domain=domain_from_manifest(req.data), pfa_budget=req.pfa_budget,
                                   scene_budget=req.scene_budget if req.use_scene else None,
                                   sunlit_only=req.sunlit_only)
    info["frames"] = req.frames
    text = (f"trained (classifier) on {info['rows']} {'sunlit ' if req.sunlit_only else ''}skin pixels; threshold "
            f"{info['threshold']:.3f} (logit) for Pfa <= {req.pfa_budget:g} on the earthlib train partition over "
            f"{info['calibration_configs']} configurations; training skin kept {info['train_coverage']:.3f}, scene "
            f"non-skin {info['pfa_scene_train']:.2e}")
    return model, info, text


__all__ = ["ClassifierDetector", "ClassifierTraining", "LINEAR_LATTICE", "SkinClassifier", "fit_linear", "load",
           "load_rows", "ratio_features", "save", "train_classifier", "train_on_dataset", "tune_threshold"]
