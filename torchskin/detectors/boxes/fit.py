"""The parts the ``boxes`` kind's trainers (``model.train_boxes``, ``model.train_quantiles``, ``model.learn``)
fit with: the settings of ``train_boxes`` (``BoxTraining``), the pinball loss and the quantile fit
(``quantile_loss``, ``fit_quantiles``), the coverage and margin terms (``soft_inside``, ``margin_violation``,
``scene_violation``), and the hard false-alarm tuning afterwards (``tune_false_alarms``, ``scene_rate``,
``train_coverage``). Takes a ``BoxModel`` but constructs none (``model`` imports this module)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, fields, replace
from typing import TYPE_CHECKING, Any

import torch

from ..features import FEATURES, distinct_configs
from .rules import NDVN_MARGIN, false_alarm_rate, inside_box

if TYPE_CHECKING:
    from .. import boxes


def _check_xy(X: torch.Tensor, Y: torch.Tensor, features: Sequence[str]) -> None:
    if (X.ndim != 2 or Y.ndim != 2 or X.shape[0] != Y.shape[0] or X.shape[1] != len(features)
            or Y.shape[1] not in (2, 3)):
        raise ValueError(f"X (n, {len(features)}) and Y (n, 2) or (n, 3) (NDGRI, NDSI[, NDVN]) expected, got "
                         f"{tuple(X.shape)} and {tuple(Y.shape)}")
    if X.shape[0] < 10:
        raise ValueError(f"at least 10 skin pixels are needed to learn boundaries, got {X.shape[0]}")


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


def fit_quantiles(model: boxes.BoxModel, X: torch.Tensor, Y: torch.Tensor, q: float, steps: int, lr: float,
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


@dataclass(frozen=True)
class BoxTraining:
    """The settings of ``train_boxes`` (see there for what each does).

    Attributes:
        features: the names of the columns of ``X``.
        hidden: network width (0: a constant box).
        steps, lr, batch, seed: Adam steps (cosine-decayed rate from ``lr``), batch size (None: all pixels), seed.
        tau: the sigmoid edges' width at the end (index units).
        margin: the distance kept from every confuser (index units, L-infinity).
        width_cost, fa_weight, spread_cost: the weights of the width, confuser and spread terms.
        domain_configs: random configurations over the training domain per step.
        domain: the training domain (k, 2) (None: the extremes of ``X``).
        per_config: every configuration weighs the same (else every pixel).
        allow: the confusers a box may hold at no cost.
        ndvn_min: d1 of the visible/NIR rule, fixed (-1: inactive).
        init_quantile, init_steps: the quantile start (``fit_quantiles``; None: ``steps // 2``).
        scene_budget, scene_weight: the scene pixels' budget and weight.
        ndvn_quantile: a learned d1 per configuration at this skin NDVN quantile (None: ``ndvn_min``).
    """

    features: Sequence[str] = FEATURES
    hidden: int = 32
    steps: int = 1500
    lr: float = 1e-2
    tau: float = 0.01
    margin: float = 0.03
    width_cost: float = 0.05
    fa_weight: float = 10.0
    domain_configs: int = 128
    batch: int | None = 32768
    seed: int = 0
    domain: Any = None
    per_config: bool = True
    spread_cost: float = 0.1
    allow: int = 0
    ndvn_min: float = -1.0
    init_quantile: float = 0.02
    init_steps: int | None = None
    scene_budget: float = 1e-4
    scene_weight: float = 3000.0
    ndvn_quantile: float | None = None

    def with_options(self, **options: Any) -> BoxTraining:
        """A copy with ``options`` (field names) changed; ``TypeError`` naming an unknown one."""
        names = {f.name for f in fields(self)}
        unknown = sorted(set(options) - names)
        if unknown:
            raise TypeError(f"train_boxes got unexpected option(s) {', '.join(unknown)}")
        return replace(self, **options)


#: ``learn`` refuses a model whose boxes hold less than this fraction of the training skin pixels
MIN_TRAIN_COVERAGE = 0.5


def train_coverage(model: boxes.BoxModel, X: torch.Tensor, Y: torch.Tensor) -> float:
    """Fraction of the training skin pixels ``Y`` (n, 2 or 3) inside the hard box of their configuration ``X``."""
    uniq, inv = distinct_configs(X)
    v = Y[:, 2] if Y.shape[1] > 2 else None
    return float(inside_box(model(uniq).index_select(0, inv), Y[:, 0], Y[:, 1], v).float().mean())


def tune_false_alarms(model: boxes.BoxModel, configs: torch.Tensor, points: torch.Tensor,
                      budget: float = 1e-3, iters: int = 30,
                      scene: tuple[torch.Tensor, torch.Tensor] | None = None, scene_budget: float = 1e-4) -> float:
    """Shrink every box about its centre (one global scale, found by bisection) until the false-alarm rate on
    ``points`` (the earthlib *train* partition) is within ``budget`` for every configuration in ``configs`` and,
    with ``scene`` (features (q, k), points (q, 2 or 3): ``load_scene_rows``), the share of those non-skin pixels
    inside their own configuration's box is within ``scene_budget``. Sets and returns ``model.scale``."""
    def ok(scale: float) -> bool:
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


def scene_rate(model: boxes.BoxModel, X: torch.Tensor, P: torch.Tensor) -> float:
    """The share of non-skin pixels (features ``X`` (q, k), (NDGRI, NDSI[, NDVN]) ``P``) that their own
    configuration's box calls skin (0 for none)."""
    if len(X) == 0:
        return 0.0
    uniq, inv = distinct_configs(X)
    with torch.no_grad():
        box = model(uniq).index_select(0, inv)
    return float(inside_box(box, P[:, 0], P[:, 1], P[:, 2] if P.shape[1] > 2 else None).float().mean())


__all__ = ["MIN_TRAIN_COVERAGE", "BoxTraining", "fit_quantiles", "margin_violation", "quantile_loss", "scene_rate",
           "scene_violation", "soft_inside", "train_coverage", "tune_false_alarms"]
