"""Configuration-dependent rules-detector boundaries: configuration features -> box (b1, b2, c1, c2, d1):
NDGRI in [b1, b2] and NDSI in [c1, c2] (the thesis's rules, eq 2.5.10, with the box chosen per configuration),
and NDVN >= d1, a visible/NIR rule on NDVN = ((g + r) - (n + s)) / (g + r + n + s), learned from generated
datasets.

Why the third rule: under eq 3.1.1 with the thesis's surface model, sunlit skin seen at grazing local
incidence (and in glints) adds a spectrally flat front-surface reflection, which pulls NDGRI and NDSI along
straight lines towards (0, 0); a box that keeps that skin must reach down in NDSI towards where litter, bark
and dry vegetation sit. Those are far darker in the visible than in the NIR (NDVN around -0.5), while skin,
from Type I to VI, stays above about -0.35, and the flat reflection only raises it towards 0. d1 is one value
for every configuration, set below the training skin's NDVN (``ndvn_rule``); with d1 = -1 the rule is inactive
(the 2-index rules alone: ``ndvn_quantile=None``).

The model is a small MLP on standardised features with an output that keeps b1 <= b2 and c1 <= c2:
    (lo_g, w_g, lo_s, w_s) -> b1 = lo_g, b2 = lo_g + softplus(w_g), c1 = lo_s, c2 = lo_s + softplus(w_s).
``hidden=0`` gives a constant box (one box for every configuration: the refitted static baseline).

Two trainers:
- ``train_boxes`` (default): per configuration, the box that covers the most sunlit skin pixels while every
  earthlib *train* spectrum stays at least ``margin`` (index units, L-infinity) outside it, for the training
  configurations and for random configurations over the training domain; a small cost per unit of box width
  keeps the edges where the skin pixels are (soft, sigmoid edges during training; hard boxes afterwards). It
  starts from the data: the conditional quantile box (``fit_quantiles``) first, then the coverage loss.
- ``train_quantiles``: the box edges as conditional quantiles of skin NDGRI and NDSI (pinball loss).
Both are followed by ``tune_false_alarms`` (a hard guarantee on the train spectra). The model is exported
to ONNX (``torchskin.export``) and run onboard without torch (``torchskin.onboard``).
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, cast

import numpy as np
import torch
from torch import nn

from .bands import INDEX_BANDS_NM
from .detect import normalized_difference, rules_detector

if TYPE_CHECKING:
    from .classifier import SkinClassifier

#: default configuration features (what an onboard computer knows: sun position and camera pointing)
FEATURES = ("sun_zenith_deg", "camera_zenith_deg", "relative_azimuth_deg")
FEATURE_UNITS = {"sun_zenith_deg": "deg", "camera_zenith_deg": "deg", "relative_azimuth_deg": "deg",
                 "range_m": "m"}
#: training domain of each feature (inputs outside it are flagged onboard)
FEATURE_DOMAIN = {"sun_zenith_deg": (0.0, 90.0), "camera_zenith_deg": (0.0, 90.0),
                  "relative_azimuth_deg": (0.0, 180.0), "range_m": (0.0, 10000.0)}
#: the columns of a box: NDGRI min, NDGRI max, NDSI min, NDSI max, NDVN min
BOX_ORDER = ("b1_ndgri_min", "b2_ndgri_max", "c1_ndsi_min", "c2_ndsi_max", "d1_ndvn_min")
#: ``ndvn_rule``: d1 = this quantile of the training skin's NDVN minus ``NDVN_MARGIN``
NDVN_QUANTILE = 0.01
NDVN_MARGIN = 0.05
#: brightness floor of the evaluation protocol and of the onboard detector: a pixel whose mean reflectance over the
#: bands is not above it is not skin (at the noise floor its indices are ratios of sensor noise; the onboard runtime
#: applies the same floor, ``min_reflectance``, recorded in the exported detector's metadata)
MIN_REFLECTANCE = 0.005
#: the dataset columns of the ELM reflectance in the four index bands (``INDEX_BANDS_NM``: g, r, n, s), in order
BAND_COLUMNS = ("r544", "r633", "r1080", "r1580")


def ratio_indices(R: torch.Tensor, zero_undefined: bool = False) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The three normalised differences of reflectance in the four index bands (g, r, n, s) = 544, 633, 1080,
    1580 nm (``INDEX_BANDS_NM``): NDGRI = (g - r) / (g + r) and NDSI = (n - s) / (n + s) (eq 2.5.10's indices)
    and NDVN = ((g + r) - (n + s)) / (g + r + n + s), the visible/NIR balance. The one home of these formulas
    (the onboard runtime evaluates them through the exported graphs).

    Args:
        R: reflectance with the four bands on the last axis, in ``INDEX_BANDS_NM`` order.
        zero_undefined: False (default): plain ratios, NaN where a band sum is 0 (undefined indices: no box
            holds them). True: 0 wherever the band sum is not positive (finite inputs for a network).

    Shape:
        R: (..., 4); each output: (...).

    Returns:
        (NDGRI, NDSI, NDVN).

    >>> g, s, v = ratio_indices(torch.tensor([[0.3, 0.6, 0.5, 0.1], [0.0, 0.0, 0.5, 0.1]]))
    >>> [round(x, 4) for x in (g[0].item(), s[0].item(), v[0].item())], bool(g[1].isnan())
    ([-0.3333, 0.6667, 0.2], True)
    >>> ratio_indices(torch.zeros(1, 4), zero_undefined=True)
    (tensor([0.]), tensor([0.]), tensor([0.]))
    """
    g, r, n, s = R.unbind(-1)
    if not zero_undefined:  # detect's normalised difference: NDGRI and NDSI exactly as ``detect.indices``
        return normalized_difference(g, r), normalized_difference(n, s), normalized_difference(g + r, n + s)
    vis, nir = g + r, n + s
    tiny = torch.finfo(R.dtype).tiny

    def nd(a, b, d):
        return torch.where(d > 0, (a - b) / d.clamp_min(tiny), torch.zeros_like(d))

    return nd(g, r, vis), nd(n, s, nir), nd(vis, nir, vis + nir)


def ndvn_rule(v: torch.Tensor, quantile: float | None = NDVN_QUANTILE, margin: float = NDVN_MARGIN) -> float:
    """d1 of the visible/NIR rule from the NDVN of training skin pixels ``v``: its ``quantile`` less ``margin``
    (-1, the rule off, when ``quantile`` is None)."""
    if quantile is None:
        return -1.0
    v = v[torch.isfinite(v)]
    if v.numel() == 0:
        return -1.0
    return max(-1.0, float(torch.quantile(v.double(), quantile)) - margin)


def config_buffers(features: Sequence[str], mean: Any = None, std: Any = None,
                   domain: Any = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The configuration inputs' standardisation (mean, std: (k,), default 0 and 1) and training domain (k, 2;
    default ``FEATURE_DOMAIN``, unbounded for other features) that box models and classifiers keep as buffers."""
    k = len(features)
    if domain is None:
        domain = [FEATURE_DOMAIN.get(f, (-1e30, 1e30)) for f in features]
    return (torch.zeros(k) if mean is None else torch.as_tensor(mean, dtype=torch.float32),
            torch.ones(k) if std is None else torch.as_tensor(std, dtype=torch.float32),
            torch.as_tensor(domain, dtype=torch.float32).reshape(k, 2))


class BoundaryModel(nn.Module):
    """Configuration features (N, k) -> boxes (N, 5) = (b1, b2, c1, c2, d1) (``BOX_ORDER``). d1, the NDVN rule:
    with ``ndvn_head``, a fifth output of the network, learned per configuration (``train_boxes``: the conditional
    ``ndvn_quantile`` of the skin's NDVN less ``NDVN_MARGIN``); else the buffer ``ndvn_min``, the same for every
    configuration (-1: inactive)."""

    # buffers (declared for type checkers; ``register_buffer`` creates them)
    mean: torch.Tensor
    std: torch.Tensor
    scale: torch.Tensor
    ndvn_min: torch.Tensor
    domain: torch.Tensor

    def __init__(self, features: Sequence[str] = FEATURES, hidden: int = 32, mean: Any = None, std: Any = None,
                 domain: Any = None, ndvn_head: bool = False):
        super().__init__()
        self.ndvn_head = bool(ndvn_head)
        outputs = 5 if self.ndvn_head else 4
        self.features = tuple(features)
        k = len(self.features)
        if hidden < 0:
            raise ValueError(f"hidden must be >= 0 (0: a constant box), got {hidden}")
        self.hidden = int(hidden)
        self.standardize = True  # False once the standardisation is folded into the first layer (export)
        mean_t, std_t, domain_t = config_buffers(self.features, mean, std, domain)
        self.register_buffer("mean", mean_t)
        self.register_buffer("std", std_t)
        self.register_buffer("scale", torch.ones(()))  # false-alarm tuning: box half-widths x scale
        self.register_buffer("ndvn_min", torch.full((), -1.0))  # d1 of the visible/NIR rule (-1: inactive)
        # the training domain of each feature (k, 2): configurations outside it are flagged onboard
        self.register_buffer("domain", domain_t)
        if hidden == 0:  # a constant box: the input weights stay zero
            first = nn.Linear(k, outputs)
            nn.init.zeros_(first.weight)
            first.weight.requires_grad_(False)
            self.net = nn.Sequential(first)
        else:
            self.net = nn.Sequential(nn.Linear(k, hidden), nn.Tanh(), nn.Linear(hidden, hidden), nn.Tanh(),
                                     nn.Linear(hidden, outputs))

    def forward(self, config: torch.Tensor) -> torch.Tensor:
        # z = (lo_g, w_g, lo_s, w_s); centre m = lo + softplus(w) / 2, half-width h = scale * softplus(w) / 2:
        # box = z P + softplus(z) Q (two small matrix products keep the exported graph short), d1 in column 5
        z = self.net((config - self.mean) / self.std if self.standardize else config)
        packed = self.net[-1].out_features == 5  # the export form (``folded``): d1 is a fifth output of the last layer
        rows = [[1.0, 1.0, 0, 0, 0], [0] * 5, [0, 0, 1.0, 1.0, 0], [0] * 5] + ([[0, 0, 0, 0, 1.0]] if packed else [])
        P = z.new_tensor(rows)  # built without in-place writes: the exported graph keeps them as constants
        q = torch.stack([0.5 * (1 - self.scale), 0.5 * (1 + self.scale)]).to(z.dtype)
        o1, o2, o3, o5 = (torch.zeros(n, dtype=z.dtype, device=z.device) for n in (1, 2, 3, 5))
        Q = torch.stack([o5, torch.cat([q, o3]), o5, torch.cat([o2, q, o1])] + ([o5] if packed else []))
        box = z @ P + nn.functional.softplus(z) @ Q
        return box if packed else box + torch.cat([o2, o2, self.ndvn_min.to(z.dtype).reshape(1)])


def folded(model: BoundaryModel) -> BoundaryModel:
    """A copy of ``model`` for export, the same function with fewer graph nodes: the feature standardisation
    folded into the first linear layer, and d1 (the NDVN rule) carried by a fifth output of the last layer
    (zero weights, bias d1) instead of being added to the boxes."""
    import copy

    m = copy.deepcopy(model).eval()
    first = cast(nn.Linear, m.net[0])
    with torch.no_grad():
        w = first.weight / m.std
        first.bias.sub_(w @ m.mean)
        first.weight.copy_(w)
        last = cast(nn.Linear, m.net[-1])
        if last.out_features == 5:  # d1 is already the fifth output (``ndvn_head``)
            m.standardize = False
            return m
        packed = nn.Linear(last.in_features, 5)
        packed.weight.zero_()
        packed.weight[:4] = last.weight
        packed.bias[:4] = last.bias
        packed.bias[4] = m.ndvn_min
        m.net[-1] = packed
    m.standardize = False
    return m


@dataclass
class TrainResult:
    model: BoundaryModel
    loss: float
    rows: int


def load_skin_rows(data_dir: str | os.PathLike, features: Sequence[str] = FEATURES,
                   sunlit_only: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """Features (n, k) and (NDGRI, NDSI, NDVN) (n, 3) of the skin pixels of a generated dataset (float32),
    sunlit and shadowed (``sunlit_only``: sunlit only), from frames whose ELM is valid (``elm_valid``, when the
    dataset has the column)."""
    X, Y = _index_rows(data_dir, features, skin=True, sunlit_only=sunlit_only)
    if len(X) == 0:
        raise ValueError(f"no usable {'sunlit ' if sunlit_only else ''}skin pixels in {str(data_dir)!r}")
    return X, Y


def load_scene_rows(data_dir: str | os.PathLike, features: Sequence[str] = FEATURES,
                    min_reflectance: float = MIN_REFLECTANCE) -> tuple[torch.Tensor, torch.Tensor]:
    """Features (n, k) and (NDGRI, NDSI, NDVN) (n, 3) of the non-skin pixels of a generated dataset (clothing,
    ground and confuser patches, in sun and in shadow, as the camera saw them; valid-ELM frames, float32): the
    scene false alarms ``learn`` holds to its scene budget. Pixels whose mean reflectance is not above
    ``min_reflectance`` (the detector's brightness floor: never skin) keep their row with NaN indices, which no
    box holds: they count in the budget's denominator, as in the evaluation, and constrain nothing."""
    return _index_rows(data_dir, features, skin=False, sunlit_only=False, floor=min_reflectance)


def _index_rows(data_dir: str | os.PathLike, features: Sequence[str], skin: bool,
                sunlit_only: bool, floor: float | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    from .dataset.files import read_valid

    t, _ = read_valid(data_dir, list(features) + ["ndgri", "ndsi", "label", "shadow", *BAND_COLUMNS])
    label = t.column("label").to_numpy(zero_copy_only=False)
    keep = label.copy() if skin else ~label
    if sunlit_only:
        keep &= ~t.column("shadow").to_numpy(zero_copy_only=False)
    X = np.stack([t.column(f).to_numpy(zero_copy_only=False) for f in features], -1)[keep]
    R = np.stack([t.column(b).to_numpy(zero_copy_only=False) for b in BAND_COLUMNS], -1)[keep].astype(np.float64)
    v = ratio_indices(torch.from_numpy(R))[2].numpy()  # NDVN in float64 (NaN where the band sum is 0)
    Y = np.stack([t.column("ndgri").to_numpy(zero_copy_only=False)[keep],
                  t.column("ndsi").to_numpy(zero_copy_only=False)[keep], v], -1)
    ok = np.isfinite(X).all(1) & np.isfinite(Y).all(1)
    if floor is not None:  # below the brightness floor: never a detection (NaN indices), still a row
        Y[~(R.mean(1) > floor)] = np.nan
        ok = np.isfinite(X).all(1)
    return torch.from_numpy(X[ok].astype(np.float32)), torch.from_numpy(Y[ok].astype(np.float32))


def domain_from_manifest(data_dir: str | os.PathLike,
                         features: Sequence[str] = FEATURES) -> list[tuple[float, float]] | None:
    """The training domain of each feature as declared by the dataset's configuration (``_manifest.json``):
    the ranges the configurations were drawn from, not the extremes of the draws. None without a manifest."""
    from .dataset.files import manifest

    man = manifest(data_dir)
    if man is None:
        return None
    cfg = man.get("config", {})
    declared = {"sun_zenith_deg": cfg.get("sun", {}).get("zenith_deg"),
                "camera_zenith_deg": cfg.get("camera", {}).get("zenith_deg"),
                "range_m": cfg.get("camera", {}).get("range_m"),
                "relative_azimuth_deg": [0.0, 180.0]}
    out = []
    for f in features:
        r = declared.get(f)
        if r is None:
            return None
        out.append((float(r[0]), float(r[1])))
    return out


def _check_xy(X: torch.Tensor, Y: torch.Tensor, features: Sequence[str]) -> None:
    if (X.ndim != 2 or Y.ndim != 2 or X.shape[0] != Y.shape[0] or X.shape[1] != len(features)
            or Y.shape[1] not in (2, 3)):
        raise ValueError(f"X (n, {len(features)}) and Y (n, 2) or (n, 3) (NDGRI, NDSI[, NDVN]) expected, got "
                         f"{tuple(X.shape)} and {tuple(Y.shape)}")
    if X.shape[0] < 10:
        raise ValueError(f"at least 10 skin pixels are needed to learn boundaries, got {X.shape[0]}")


def _initial_model(X: torch.Tensor, Y: torch.Tensor, features, hidden: int, q: float, seed: int,
                   domain=None, ndvn_quantile: float | None = None) -> BoundaryModel:
    """A model that starts at the pooled (q, 1 - q) quantile box (and, with ``ndvn_quantile``, a learned d1 at
    the pooled NDVN quantile of ``Y[:, 2]`` less ``NDVN_MARGIN``), with small deterministic weights (``seed``)
    and the training ``domain`` ((k, 2); default: the extremes of ``X``)."""
    g = torch.Generator().manual_seed(seed)
    if domain is None:
        domain = torch.stack([X.min(0).values, X.max(0).values], -1)
    head = ndvn_quantile is not None
    model = BoundaryModel(features, hidden, X.mean(0), X.std(0).clamp_min(1e-6), domain, ndvn_head=head)
    with torch.no_grad():
        for p in model.net.parameters():
            if p.requires_grad:
                p.copy_(torch.randn(p.shape, generator=g) * (0.3 / math.sqrt(max(p.shape[-1], 1))))
        last = cast(nn.Linear, model.net[-1])
        if hidden:
            last.weight.mul_(0.1)
        qg = torch.quantile(Y[:, 0], torch.tensor([q, 1 - q]))
        qs = torch.quantile(Y[:, 1], torch.tensor([q, 1 - q]))
        inv_sp = lambda w: torch.log(torch.expm1(w.clamp_min(1e-3)))  # noqa: E731
        start = [qg[0], inv_sp(qg[1] - qg[0]), qs[0], inv_sp(qs[1] - qs[0])]
        if head:
            start.append(torch.quantile(Y[:, 2], float(cast(float, ndvn_quantile))) - NDVN_MARGIN)
        last.bias.copy_(torch.stack(start))
    return model


def quantile_loss(box: torch.Tensor, Y: torch.Tensor, q: float, w: torch.Tensor | None = None,
                  ndvn_quantile: float | None = None) -> torch.Tensor:
    """The pinball loss of the box edges as conditional quantiles of (NDGRI, NDSI) ``Y`` (n, 2+): b1, c1 at
    ``q``, b2, c2 at ``1 - q``, each pixel weighted by ``w`` (n,) (None: 1); with ``ndvn_quantile`` (and a fifth
    box column, a third of ``Y``), d1 at that quantile of NDVN less ``NDVN_MARGIN``."""
    cols = [Y[:, 0] - box[:, 0], Y[:, 0] - box[:, 1], Y[:, 1] - box[:, 2], Y[:, 1] - box[:, 3]]
    levels = [q, 1 - q, q, 1 - q]
    if ndvn_quantile is not None and box.shape[1] > 4 and Y.shape[1] > 2:
        cols.append(Y[:, 2] - NDVN_MARGIN - box[:, 4])
        levels.append(ndvn_quantile)
    e = torch.stack(cols, -1)
    lv = box.new_tensor(levels)
    loss = torch.maximum(lv * e, (lv - 1) * e).sum(-1)
    return (loss if w is None else loss * w).mean()


def fit_quantiles(model: BoundaryModel, X: torch.Tensor, Y: torch.Tensor, q: float, steps: int, lr: float,
                  w: torch.Tensor | None = None, batch: int | None = None, g: torch.Generator | None = None,
                  decay: bool = False, ndvn_quantile: float | None = None) -> float:
    """Adam on ``quantile_loss`` (in place): ``model``'s boxes become the conditional ``q`` / ``1 - q`` quantiles
    of ``Y`` given ``X``, pixels weighted by ``w``, on random batches of ``batch`` pixels drawn with ``g`` (None:
    all of them), the learning rate decaying from ``lr`` to ``lr``/100 when ``decay`` (cosine). Pixels that share
    a configuration share its box (one forward pass per distinct configuration). Returns the last loss."""
    cfg, inv = distinct_configs(X)
    opt = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, max(1, steps), eta_min=lr * 0.01) if decay else None
    loss = torch.tensor(0.0)
    for _ in range(steps):
        if batch is not None and batch < len(Y):
            idx = torch.randint(len(Y), (batch,), generator=g)
            yb, ib, wb = Y[idx], inv[idx], None if w is None else w[idx]
        else:
            yb, ib, wb = Y, inv, w
        opt.zero_grad()
        loss = quantile_loss(model(cfg).index_select(0, ib), yb, q, wb, ndvn_quantile)
        loss.backward()
        opt.step()
        if sched is not None:
            sched.step()
    return float(loss.detach())


def train_quantiles(X: torch.Tensor, Y: torch.Tensor, q: float = 0.01, features: Sequence[str] = FEATURES,
                    hidden: int = 32, steps: int = 2000, lr: float = 3e-3, seed: int = 0, domain: Any = None) -> TrainResult:
    """Fit the box as conditional quantiles: b1, c1 at ``q`` and b2, c2 at ``1 - q`` of sunlit skin NDGRI and
    NDSI given the configuration features (full-batch Adam on the pinball loss, ``fit_quantiles``;
    deterministic in ``seed``)."""
    if not (0.0 < q < 0.5):
        raise ValueError(f"q must lie in (0, 0.5), got {q}")
    _check_xy(X, Y, features)
    model = _initial_model(X, Y, features, hidden, q, seed, domain)
    loss = fit_quantiles(model, X, Y, q, steps, lr)
    return TrainResult(model.eval(), loss, X.shape[0])


def soft_inside(boxes: torch.Tensor, points: torch.Tensor, tau: float) -> torch.Tensor:
    """Smooth indicator that (NDGRI, NDSI) ``points`` (n, 2+) lie in ``boxes`` (n, 4+): the product of four
    sigmoids of the edge distances over ``tau`` (index units; the NDVN rule is not part of it)."""
    g, s = points[:, 0], points[:, 1]
    d = torch.stack([g - boxes[:, 0], boxes[:, 1] - g, s - boxes[:, 2], boxes[:, 3] - s], -1)
    return torch.sigmoid(d / tau).prod(-1)


def margin_violation(boxes: torch.Tensor, points: torch.Tensor, margin: float, allow: int = 0) -> torch.Tensor:
    """Per box (N, 4), the summed violation of ``points`` (n, 2) that lie inside it or within ``margin``
    (L-infinity, index units) of it: sum_j relu(min(edge distances_j) + margin), less the ``allow`` largest
    violations (the points the false-alarm budget lets a box hold)."""
    g, s = points[:, 0][None], points[:, 1][None]
    b = boxes[:, :, None]
    depth = torch.minimum(torch.minimum(g - b[:, 0], b[:, 1] - g), torch.minimum(s - b[:, 2], b[:, 3] - s))
    v = torch.relu(depth + margin)
    if boxes.shape[1] > 4 and points.shape[1] > 2:  # points the box's own NDVN rule rejects need no margin
        v = v * (points[:, 2][None] >= b[:, 4].detach())
    total = v.sum(-1)
    if allow > 0:
        total = total - v.topk(min(int(allow), v.shape[-1]), dim=-1).values.sum(-1)
    return total


def scene_violation(boxes: torch.Tensor, points: torch.Tensor, margin: float, allow: int = 0) -> torch.Tensor:
    """The summed violation of scene non-skin ``points`` (n, 2) each against its own configuration's box (n, 4+):
    sum_j relu(min(edge distances_j) + margin), less the ``allow`` largest (the pixels the scene budget lets the
    boxes hold)."""
    g, s = points[:, 0], points[:, 1]
    depth = torch.minimum(torch.minimum(g - boxes[:, 0], boxes[:, 1] - g),
                          torch.minimum(s - boxes[:, 2], boxes[:, 3] - s))
    v = torch.relu(depth + margin)
    if boxes.shape[1] > 4 and points.shape[1] > 2:  # pixels the box's own NDVN rule rejects need no margin
        v = v * (points[:, 2] >= boxes[:, 4].detach())
    total = v.sum()
    if allow > 0:
        total = total - v.topk(min(int(allow), v.numel())).values.sum()
    return total


def train_boxes(X: torch.Tensor, Y: torch.Tensor, confusers: torch.Tensor, features: Sequence[str] = FEATURES,
                hidden: int = 32,
                steps: int = 1500, lr: float = 1e-2, tau: float = 0.01, margin: float = 0.03,
                width_cost: float = 0.05, fa_weight: float = 10.0, domain_configs: int = 128,
                batch: int | None = 32768, seed: int = 0, domain: Any = None, per_config: bool = True,
                spread_cost: float = 0.1, allow: int = 0, ndvn_min: float = -1.0, init_quantile: float = 0.02,
                init_steps: int | None = None, scene: tuple[torch.Tensor, torch.Tensor] | None = None,
                scene_budget: float = 1e-4, scene_weight: float = 3000.0,
                ndvn_quantile: float | None = None) -> TrainResult:
    """Learn the box that, per configuration, covers the most sunlit skin pixels ``Y`` (n, 2) given their
    configuration features ``X`` (n, k), while every ``confusers`` point (m, 2) (the earthlib *train* spectra)
    stays ``margin`` outside it, for ``domain_configs`` training configurations and as many random
    configurations over the training domain per step:

        loss = -mean_i w_i soft_inside(box(x_i), y_i) + width_cost * mean_i w_i width(box(x_i))
               + fa_weight * mean_configs margin_violation(box(config), confusers)
               + spread_cost * mean_configs |box(config) - mean_configs box|^2

    with w_i = 1 / (the number of pixels of pixel i's configuration), normalised to mean 1, when
    ``per_config`` (default): every configuration weighs the same, as in the mean Pd over configurations,
    so geometries that show little skin (a camera overhead) are not traded away; else w_i = 1. The spread
    term pulls every configuration's box towards their mean: the box moves with the configuration only where
    the skin pixels pay for it (without it, boxes shrank where the data are thin: camera-overhead Pd fell to
    0.90-0.96 on held-out data against 0.97-0.99 for a single refitted box). ``allow``: the number of confusers
    a box may hold at no cost (the ``allow`` largest violations are not counted): ``learn`` sets it to the
    false-alarm budget, floor(pfa_budget x number of confusers), so that training and the hard tuning
    afterwards (``tune_false_alarms``) enforce the same budget. ``ndvn_min``: d1 of the visible/NIR rule (fixed during training; -1
    inactive): with (m, 3) ``confusers`` (NDGRI, NDSI, NDVN), those it rejects need no margin from the box.
    ``scene``: the training dataset's own non-skin pixels, (features (q, k), (NDGRI, NDSI, NDVN) (q, 3))
    (``load_scene_rows``): each must stay ``margin`` outside its own configuration's box, all but the fraction
    ``scene_budget`` of them (``scene_violation`` on a batch, weight ``scene_weight`` per pixel of the batch: a
    pixel at the margin's depth, 0.03, costs as much as ~100 skin pixels' coverage at the default 3000; at 10 the
    training ignored them and the hard tuning afterwards had to shrink every box, to 0.41 of the skin):
    the confusers as the camera saw them, shadowed and back-lit, per configuration. (Each pixel holding also the
    boxes of configurations within 10° of its own cut the held-out scene Pfa from 6.6e-4 to 2.8e-4 and Pd sunlit
    from 0.80 to 0.78: not kept; ``evaluate.calibrate_to_budget`` closes the gap on the held-out set.)
    ``ndvn_quantile`` (with (n, 3)
    ``Y``): d1 becomes a fifth output of the network, learned per configuration as the conditional
    ``ndvn_quantile`` of the skin's NDVN less ``NDVN_MARGIN`` (pinball loss, in the start and alongside the
    coverage loss; ``ndvn_min`` is then ignored), and the confusers and scene pixels each box's own d1 rejects
    need no margin. A pooled d1 fails at low sun: level ELM panels lit by a blue sky against skin facing a red
    sun pull the skin's NDVN down in those configurations only, and the pooled quantile with them.

    The start comes from the data, not from the seed: first the boxes are fitted as the conditional
    ``init_quantile`` / ``1 - init_quantile`` quantiles of the skin's NDGRI and NDSI given the configuration
    (``fit_quantiles``, ``init_steps`` steps, default ``steps // 2``, the same weights w_i), a box that already
    follows the skin from configuration to configuration (~92 % of the pixels at 0.02); the loss above then
    moves its edges. (Started instead from one pooled box with random weights, the optimisation left part of
    the configurations' skin outside in 7 of 10 runs on a diagonal test set, and which runs did depended on the
    machine's float rounding.)

    Adam on random batches of ``batch`` pixels (None: all of them), deterministic in ``seed``; the sigmoid
    edges sharpen from 3 tau to tau over the first half of the steps and the learning rate decays from ``lr``
    to ``lr``/100 (cosine): at a constant rate, late steps on the sharp edges could throw the box off the data,
    where no gradient brings it back. ``domain`` (k, 2): the training domain
    (default: the extremes of ``X``; ``domain_from_manifest`` gives the declared ranges).

    Shape:
        X: (n, k); Y: (n, 2) or (n, 3) (NDVN unused here); confusers: (m, 2) or (m, 3); domain: (k, 2).

    Returns:
        ``TrainResult``: the model (eval mode, ``scale`` 1: ``tune_false_alarms`` comes next), the last loss and
        the number of skin pixels."""
    for name, v, bound in (("tau", tau, 0.0), ("margin", margin, -1e-12), ("width_cost", width_cost, -1e-12),
                           ("fa_weight", fa_weight, -1e-12), ("spread_cost", spread_cost, -1e-12)):
        if not (v > bound) or not math.isfinite(v):
            raise ValueError(f"{name} must be {'positive' if bound == 0 else 'non-negative'} and finite, got {v}")
    if not (0.0 < init_quantile < 0.5):
        raise ValueError(f"init_quantile must lie in (0, 0.5), got {init_quantile}")
    init_steps = steps // 2 if init_steps is None else int(init_steps)
    if init_steps < 0:
        raise ValueError(f"init_steps must be >= 0, got {init_steps}")
    _check_xy(X, Y, features)
    if confusers.ndim != 2 or confusers.shape[1] not in (2, 3) or confusers.shape[0] == 0:
        raise ValueError(f"confusers must be (m, 2) or (m, 3) (NDGRI, NDSI[, NDVN]) points, got "
                         f"{tuple(confusers.shape)}")
    head = ndvn_quantile is not None and Y.shape[1] > 2
    if head and not (0.0 < float(cast(float, ndvn_quantile)) < 0.5):
        raise ValueError(f"ndvn_quantile must lie in (0, 0.5), got {ndvn_quantile}")
    if head and confusers.shape[1] < 3:
        raise ValueError("a learned NDVN rule (ndvn_quantile) needs (m, 3) confusers (NDGRI, NDSI, NDVN)")
    if not head:
        if confusers.shape[1] == 3 and ndvn_min > -1.0:
            confusers = confusers[confusers[:, 2] >= ndvn_min]  # the others fail the visible/NIR rule anyway
        confusers = confusers[:, :2]
        Y = Y[:, :2]
    if confusers.shape[0] == 0:
        confusers = torch.full((1, confusers.shape[1]), 10.0)  # nothing left to keep out
    model = _initial_model(X, Y, features, hidden, init_quantile, seed, domain,
                           ndvn_quantile if head else None)
    model.ndvn_min.fill_(-1.0 if head else float(ndvn_min))
    vq = ndvn_quantile if head else None
    g = torch.Generator().manual_seed(seed + 1)
    train_cfg, inv = distinct_configs(X)  # pixels share their configuration: one box per distinct one
    counts = torch.bincount(inv, minlength=len(train_cfg)).to(Y.dtype)
    w = (len(Y) / len(train_cfg)) / counts.index_select(0, inv) if per_config else torch.ones(len(Y), dtype=Y.dtype)
    fit_quantiles(model, X, Y, init_quantile, init_steps, lr, w, batch, g, decay=True,
                  ndvn_quantile=vq)  # the start: from the data
    lo, hi = model.domain[:, 0], model.domain[:, 1]
    # only the spectra near the skin pixels can meet a box (the hard tuning afterwards checks them all)
    qy = torch.quantile(Y[:, :2], torch.tensor([0.01, 0.99]), dim=0)  # (2, 2)
    near = ((confusers[:, :2] >= qy[0] - 0.25) & (confusers[:, :2] <= qy[1] + 0.25)).all(-1)
    C = confusers[near].float()
    if scene is not None:
        sX, sP = scene
        if not head and ndvn_min > -1.0 and sP.shape[1] > 2:
            keep = sP[:, 2] >= ndvn_min  # the visible/NIR rule rejects the others
            sX, sP = sX[keep], sP[keep]
        near_s = ((sP[:, :2] >= qy[0] - 0.25) & (sP[:, :2] <= qy[1] + 0.25)).all(-1)
        sX, sP = sX[near_s], sP[near_s, :(3 if head else 2)].float()
        scene_cfg, scene_inv = distinct_configs(sX) if len(sX) else (sX, torch.zeros(0, dtype=torch.long))
        n_scene = len(scene[0])  # the budget is a fraction of all of them
    opt = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, max(1, steps), eta_min=lr * 0.01)
    loss = torch.tensor(0.0)
    for step in range(steps):
        t = tau * (3.0 - 2.0 * min(1.0, step / max(1, steps // 2)))
        cfg = torch.cat([train_cfg[torch.randint(len(train_cfg), (min(len(train_cfg), domain_configs),), generator=g)],
                         lo + (hi - lo) * torch.rand(domain_configs, X.shape[1], generator=g)])
        if batch is not None and batch < len(Y):
            idx = torch.randint(len(Y), (batch,), generator=g)
            yb, ib, wb = Y[idx], inv[idx], w[idx]
        else:
            yb, ib, wb = Y, inv, w
        opt.zero_grad()
        box = model(train_cfg).index_select(0, ib)  # (its backward accumulates deterministically)
        cover = (soft_inside(box, yb, t) * wb).mean()
        width = ((box[:, 1] - box[:, 0] + box[:, 3] - box[:, 2]) * wb).mean()
        bc = model(cfg)
        fa = margin_violation(bc, C, margin, allow).mean()
        spread = (bc[:, :4] - bc[:, :4].mean(0)).square().sum(-1).mean()
        loss = -cover + width_cost * width + fa_weight * fa + spread_cost * spread
        if vq is not None:  # d1 follows the skin's NDVN quantile per configuration
            e = yb[:, 2] - NDVN_MARGIN - box[:, 4]
            loss = loss + (torch.maximum(vq * e, (vq - 1) * e) * wb).mean()
        if scene is not None and len(sP):
            nb = min(len(sP), batch or len(sP))
            j = torch.randint(len(sP), (nb,), generator=g) if nb < len(sP) else torch.arange(len(sP))
            # the budget's share of this batch: the near pixels stand for all n_scene of them
            allow_b = int(math.floor(scene_budget * n_scene * nb / len(sP)))
            sb = model(scene_cfg).index_select(0, scene_inv[j])
            loss = loss + scene_weight * scene_violation(sb, sP[j], margin, allow_b) / nb
        loss.backward()
        opt.step()
        sched.step()
    return TrainResult(model.eval(), float(loss.detach()), X.shape[0])


def tuning_configs(model: BoundaryModel | SkinClassifier, X: torch.Tensor, grid: int = 10) -> torch.Tensor:
    """The configurations the false-alarm budget is enforced on: every distinct training configuration in
    ``X`` and a ``grid``^k lattice over the model's training domain."""
    uniq = distinct_configs(X)[0].float()
    axes = [torch.linspace(float(lo), float(hi), grid) for lo, hi in model.domain]
    lattice = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, len(axes))
    return torch.cat([uniq, lattice])


METHODS = ("boxes", "quantiles")


def learn(X: torch.Tensor, Y: torch.Tensor, method: str = "boxes", pfa_budget: float = 1e-3,
          confusers: torch.Tensor | None = None, ndvn_quantile: float | None = NDVN_QUANTILE,
          scene: tuple[torch.Tensor, torch.Tensor] | None = None, scene_budget: float = 1e-4,
          **options: Any) -> tuple[BoundaryModel, dict]:
    """Learn the configuration-dependent boxes: train (``train_boxes`` or ``train_quantiles``), then enforce the
    false-alarm budget on the earthlib train partition (``tune_false_alarms`` over ``tuning_configs``). With
    (n, 3) skin points ``Y`` and (m, 3) confusers the visible/NIR rule is set first (``ndvn_rule`` of the
    skin's NDVN at ``ndvn_quantile``; None: no such rule).

    Args:
        X: configuration features of the sunlit skin pixels (``FEATURES`` order and units).
        Y: their (NDGRI, NDSI[, NDVN]) (``load_skin_rows``).
        method: "boxes" (``train_boxes``) or "quantiles" (``train_quantiles``).
        pfa_budget: the largest fraction of ``confusers`` any box may hold, in [0, 1).
        confusers: (NDGRI, NDSI[, NDVN]) points to keep out (default: ``confuser_indices("train")``).
        ndvn_quantile: the skin NDVN quantile d1 is set from (None: the rule is off, d1 = -1).
        scene: the training dataset's non-skin pixels (``load_scene_rows``): held to ``scene_budget`` in training
            (``train_boxes``) and in the tuning (``tune_false_alarms``); None: earthlib spectra only.
        scene_budget: the largest share of ``scene`` pixels the boxes may call skin, in [0, 1).
        **options: passed to the trainer (``steps``, ``hidden``, ``margin``, ``seed``, ...).

    Shape:
        X: (n, k); Y: (n, 2) or (n, 3); confusers: (m, 2) or (m, 3).

    Returns:
        The model (eval mode) and a summary: method, rows, loss, scale, ndvn_min, pfa_budget, pfa_train_worst,
        train_coverage, calibration_configs (the number of tuning configurations), options.

    Raises ``ValueError`` on a bad method or budget, or when the boxes hold less than ``MIN_TRAIN_COVERAGE`` of
    the training skin pixels. (No doctest: even a tiny run trains for seconds; see tests/test_boundaries_onnx.py.)
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if not (0.0 <= pfa_budget < 1.0):
        raise ValueError(f"pfa_budget must lie in [0, 1), got {pfa_budget}")
    if not (0.0 <= scene_budget < 1.0):
        raise ValueError(f"scene_budget must lie in [0, 1), got {scene_budget}")
    if scene is not None and (scene[0].ndim != 2 or scene[0].shape[1] != X.shape[1] or scene[1].ndim != 2
                              or scene[1].shape[0] != scene[0].shape[0] or scene[1].shape[1] not in (2, 3)):
        raise ValueError(f"scene must be (features (q, {X.shape[1]}), points (q, 2 or 3)), got "
                         f"{tuple(scene[0].shape)} and {tuple(scene[1].shape)}")
    C = confuser_indices("train") if confusers is None else confusers
    learned_d1 = method == "boxes" and ndvn_quantile is not None and Y.ndim == 2 and Y.shape[1] > 2 \
        and C.shape[1] > 2
    d1 = ndvn_rule(Y[:, 2], ndvn_quantile) if Y.ndim == 2 and Y.shape[1] > 2 and C.shape[1] > 2 else -1.0
    if method == "boxes":
        options.setdefault("allow", int(math.floor(pfa_budget * C.shape[0])))
        res = train_boxes(X, Y, C, ndvn_min=d1, scene=scene, scene_budget=scene_budget,
                          ndvn_quantile=ndvn_quantile if learned_d1 else None, **options)
    else:
        res = train_quantiles(X, Y[:, :2], **options)
        res.model.ndvn_min.fill_(d1)
    cfg = tuning_configs(res.model, X)
    scale = tune_false_alarms(res.model, cfg, C, pfa_budget, scene=scene, scene_budget=scene_budget)
    with torch.no_grad():
        boxes = res.model(cfg)
        pfa_train = float(false_alarm_rate(boxes, C).max())
        d1_range = [float(boxes[:, 4].min()), float(boxes[:, 4].max())]
        pfa_scene = scene_rate(res.model, *scene) if scene is not None else None
        coverage = train_coverage(res.model, X, Y)
    if coverage < MIN_TRAIN_COVERAGE:
        raise ValueError(f"training failed: the learned boxes hold only {coverage:.3f} of the training skin pixels "
                         f"(< {MIN_TRAIN_COVERAGE}); the optimisation left the data. Try another seed (--seed) or "
                         "fewer hidden units (--hidden), or check the dataset and the false-alarm budget")
    return res.model, {"method": method, "rows": res.rows, "loss": res.loss, "scale": scale,
                       "ndvn_min": d1_range[0], "ndvn_range": d1_range, "ndvn_learned": learned_d1,
                       "pfa_budget": pfa_budget, "pfa_train_worst": pfa_train, "train_coverage": coverage,
                       "scene_budget": scene_budget if scene is not None else None, "pfa_scene_train": pfa_scene,
                       "scene_pixels": int(scene[0].shape[0]) if scene is not None else 0,
                       # the key keeps its old name: checkpoints and model cards carry it
                       "calibration_configs": int(cfg.shape[0]), "options": options}


#: ``learn`` refuses a model whose boxes hold less than this fraction of the training skin pixels
MIN_TRAIN_COVERAGE = 0.5


def distinct_configs(X: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The distinct rows of ``X`` (n, k) and, per row of ``X``, the index of its distinct row."""
    uniq, inv = np.unique(X.numpy(), axis=0, return_inverse=True)
    return torch.from_numpy(uniq), torch.from_numpy(inv.reshape(-1))


def train_coverage(model: BoundaryModel, X: torch.Tensor, Y: torch.Tensor) -> float:
    """Fraction of the training skin pixels ``Y`` (n, 2 or 3) inside the hard box of their configuration ``X``."""
    uniq, inv = distinct_configs(X)
    v = Y[:, 2] if Y.shape[1] > 2 else None
    return float(inside_box(model(uniq).index_select(0, inv), Y[:, 0], Y[:, 1], v).float().mean())


def save(model: BoundaryModel, path: str | os.PathLike, meta: dict | None = None) -> None:
    """A torch checkpoint: state, features and hidden size (+ metadata), written atomically through a buffer:
    the same model gives the same bytes."""
    from .io import save_torch

    save_torch(path, {"state_dict": model.state_dict(), "features": list(model.features), "hidden": model.hidden,
                      "ndvn_head": model.ndvn_head, "meta": meta or {}})


def load(path: str | os.PathLike) -> BoundaryModel:
    """A ``BoundaryModel`` from a checkpoint written by ``save`` (older checkpoints without a stored domain or
    NDVN rule get the defaults), in eval mode."""
    ck = torch.load(path, map_location="cpu", weights_only=True)
    m = BoundaryModel(ck["features"], ck["hidden"], ndvn_head=bool(ck.get("ndvn_head", False)))
    state = dict(ck["state_dict"])
    state.setdefault("domain", m.domain)  # checkpoints written before the domain was stored
    state.setdefault("ndvn_min", m.ndvn_min)  # and before the visible/NIR rule
    m.load_state_dict(state)
    return m.eval()


def confuser_indices(part: str = "train") -> torch.Tensor:
    """(NDGRI, NDSI, NDVN) of the earthlib spectra of one partition, (n, 3): geometry-independent (Lambertian:
    a geometric factor scales every band alike). Spectra whose indices are undefined (zero reflectance in a
    band pair) are left out: no box holds them."""
    from .confusers import band_reflectance

    _, R = band_reflectance(INDEX_BANDS_NM, part)
    pts = torch.stack(ratio_indices(R.float()), -1)
    return pts[torch.isfinite(pts).all(-1)]


def inside_box(boxes: torch.Tensor, g: torch.Tensor, s: torch.Tensor, v: torch.Tensor | None = None) -> torch.Tensor:
    """The rules detector (eq 2.5.10 with a box per configuration): whether (NDGRI, NDSI) = (``g``, ``s``) lies in
    the box, b1 <= g <= b2 and c1 <= s <= c2 (edges included), and, with ``v`` (NDVN) and a fifth column,
    NDVN >= d1. The box test itself is ``detect.rules_detector``'s (the onboard runtime's is the exported
    detector graph).

    Args:
        boxes: (b1, b2, c1, c2[, d1]) on axis 1 (``BOX_ORDER``).
        g, s: NDGRI and NDSI.
        v: NDVN (None: the fifth rule is not applied).

    Shape:
        boxes: (N, 4 or 5, ...); g, s, v and the result: broadcast with ``boxes[:, 0]``, e.g. (N, ...).

    Returns:
        A bool tensor, True inside.

    >>> boxes = torch.tensor([[-0.5, 0.0, 0.3, 0.9, -0.4]])
    >>> inside_box(boxes, torch.tensor([-0.3, 0.2]), torch.tensor([0.6, 0.6]))
    tensor([ True, False])
    >>> inside_box(boxes, torch.tensor([-0.3]), torch.tensor([0.6]), torch.tensor([-0.6]))
    tensor([False])
    """
    ok = rules_detector(g, s, torch.movedim(boxes[:, :4], 1, -1))  # eq 2.5.10's test, the box on the last axis
    if v is not None and boxes.shape[1] > 4:
        ok = ok & (v >= boxes[:, 4])
    return ok


def false_alarm_rate(boxes: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Per box (N, 4 or 5): the fraction of ``points`` (n, 2 or 3: NDGRI, NDSI[, NDVN]) inside it."""
    v = points[:, 2][None] if points.shape[1] > 2 else None
    return inside_box(boxes[:, :, None], points[:, 0][None], points[:, 1][None], v).float().mean(-1)


def tune_false_alarms(model: BoundaryModel, configs: torch.Tensor, points: torch.Tensor,
                      budget: float = 1e-3, iters: int = 30,
                      scene: tuple[torch.Tensor, torch.Tensor] | None = None, scene_budget: float = 1e-4) -> float:
    """Shrink every box about its centre (one global scale, found by bisection) until the false-alarm rate on
    ``points`` (the earthlib *train* partition) is within ``budget`` for every configuration in ``configs`` and,
    with ``scene`` (features (q, k), points (q, 2 or 3): ``load_scene_rows``), the share of those non-skin pixels
    inside their own configuration's box is within ``scene_budget``. Sets and returns ``model.scale``."""
    def ok(scale):
        model.scale.fill_(scale)
        with torch.no_grad():
            if float(false_alarm_rate(model(configs), points).max()) > budget:
                return False
            return scene is None or scene_rate(model, *scene) <= scene_budget

    if ok(1.0):
        return 1.0
    lo, hi = 0.0, 1.0
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if ok(mid) else (lo, mid)
    ok(lo)
    return lo


def scene_rate(model: BoundaryModel, X: torch.Tensor, P: torch.Tensor) -> float:
    """The share of non-skin pixels (features ``X`` (q, k), (NDGRI, NDSI[, NDVN]) ``P``) that their own
    configuration's box calls skin (0 for none)."""
    if len(X) == 0:
        return 0.0
    uniq, inv = distinct_configs(X)
    with torch.no_grad():
        box = model(uniq).index_select(0, inv)
    return float(inside_box(box, P[:, 0], P[:, 1], P[:, 2] if P.shape[1] > 2 else None).float().mean())
