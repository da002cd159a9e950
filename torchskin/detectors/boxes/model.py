"""The ``boxes`` detector kind's model, ``BoxModel`` (registered by ``torchskin.detectors.registry``), and what
constructs one: its data-driven start (``_initial_model``), the trainers (``train_boxes``, ``train_quantiles``,
``learn``, ``train_on_dataset``: the trainers construct the model and ``BoxModel.from_training`` calls them, so
they share this module) and its checkpoints (``save``, ``load``). The package's docstring
(``torchskin.detectors.boxes``) says what the boxes are and how they are learned."""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar, cast

import torch
from torch import nn

from ...bands import INDEX_BANDS_NM
from ...errors import Failure
from ..features import (
    FEATURES,
    config_buffers,
    confuser_indices,
    distinct_configs,
    domain_from_manifest,
    ratio_indices,
    tuning_configs,
)
from ..protocol import KindOption, PipelineRun, write_checkpoint
from .data import load_scene_rows, load_skin_rows
from .fit import (
    MIN_TRAIN_COVERAGE,
    BoxTraining,
    _check_xy,
    fit_quantiles,
    margin_violation,
    scene_rate,
    scene_violation,
    soft_inside,
    train_coverage,
    tune_false_alarms,
)
from .onnx import BoxDetector, boundaries_graph, edge_detector_graph
from .rules import NDVN_MARGIN, NDVN_QUANTILE, false_alarm_rate, inside_box, ndvn_rule

if TYPE_CHECKING:
    import onnx

    from ..protocol import CalibrationData, TrainRequest


class BoxModel(nn.Module):
    """Configuration features (N, k) -> boxes (N, 5) = (b1, b2, c1, c2, d1) (``BOX_ORDER``). d1, the NDVN rule:
    with ``ndvn_head``, a fifth output of the network, learned per configuration (``train_boxes``: the conditional
    ``ndvn_quantile`` of the skin's NDVN less ``NDVN_MARGIN``); else the buffer ``ndvn_min``, the same for every
    configuration (-1: inactive).

    The ``boxes`` detector kind (``protocol.BoxDetectorModel``): ``decide`` applies the rules to a pixel's indices,
    ``detector_graph`` / ``boundaries_graph`` are its ONNX exports, ``checkpoint`` / ``from_checkpoint`` its torch
    checkpoint (``save`` / ``load``)."""

    kind: ClassVar[str] = "boxes"
    #: the training methods of this kind (``learn``)
    methods: ClassVar[tuple[str, ...]] = ("boxes", "quantiles")
    #: the band centres (nm) its training and evaluation data must hold (``registry.required_bands``): the four
    #: index bands, whose columns (``BAND_COLUMNS``) it reads
    required_bands: ClassVar[tuple[float, ...]] = INDEX_BANDS_NM
    #: its training options, each a ``torchskin train`` flag (``protocol.KindOption``; ``train_on_dataset``)
    options: ClassVar[tuple[KindOption, ...]] = (
        KindOption("margin", 0.03, "boxes: distance (index units) kept from every earthlib train spectrum "
                                   "(default 0.03)"),
        KindOption("width_cost", 0.05, "boxes: cost per unit of box width, keeps the box tight (default 0.05)"),
        KindOption("spread_cost", 0.1, "boxes: cost of the boxes' spread over configurations (squared distance to "
                                       "their mean): the box moves with the configuration only where the data pay "
                                       "for it (default 0.1)"),
        KindOption("q", 0.15, "quantiles: quantile of the box edges (default 0.15)"),
        KindOption("ndvn_rule", True, "boxes and quantiles: no visible/NIR rule (NDVN >= d1, d1 just below the "
                                      "training skin's NDVN): the thesis's two indices alone", bool, "--no-ndvn-rule"))
    #: its methods in ``torchskin train --method``'s help
    method_help: ClassVar[str] = ("boxes: most sunlit skin per configuration with the earthlib train spectra kept a "
                                  "margin outside (default); quantiles: conditional quantiles of NDGRI and NDSI "
                                  "(pinball loss)")
    #: its detector graph runs on the onboard box head (``onboard.detector_head``), and meets the onboard budget
    #: (five edge forms, ~4 ms per 1024² frame on 2 cores: ``evaluation.select_detector`` may ship it)
    onboard_head: ClassVar[str] = "boxes"
    onboard_selectable: ClassVar[bool] = True
    #: the model card's words for its ``detector.onnx`` score
    card_score: ClassVar[str] = ("box models: the smallest margin to a box edge in index units times the band-pair "
                                 "sum (g + r or n + s)")
    #: ``make demo`` trains the boxes (exported as ``boundaries.onnx``) and one box for every configuration
    #: (``--hidden 0``, ``baseline_box.onnx``)
    pipeline_runs: ClassVar[tuple[PipelineRun, ...]] = (
        PipelineRun("boundaries", ("--method", "boxes"), "--model"),
        PipelineRun("baseline_box", ("--method", "boxes", "--hidden", "0"), "--baseline"))

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

    # ---------------------------------------------------------------- the detector kind (protocol.BoxDetectorModel)
    @torch.no_grad()
    def boxes(self, config: torch.Tensor) -> torch.Tensor:
        """The boxes (n, 5) of configurations (n, k) (float32, no graph)."""
        return self(torch.as_tensor(config, dtype=torch.float32)).detach()

    @torch.no_grad()
    def decide(self, R: torch.Tensor, config: torch.Tensor) -> torch.Tensor:
        """Skin mask (n,) of reflectance (n, 4) under configurations (n, k): (NDGRI, NDSI, NDVN) of ``R``
        (``ratio_indices``) inside the configuration's box (``inside_box``)."""
        g, s, v = ratio_indices(R)
        return inside_box(self.boxes(config), g, s, v)

    def boundaries_graph(self, meta: dict[str, str]) -> onnx.ModelProto:
        """``boundaries.onnx``: config (N, k) -> boxes (N, 5) (the ``folded`` model), with metadata ``meta``."""
        return boundaries_graph(self, meta)

    def detector_graph(self, meta: dict[str, str]) -> onnx.ModelProto:
        """``detector.onnx``: the boundaries graph plus the edge-form head (``edge_detector_graph``)."""
        return edge_detector_graph(boundaries_graph(self, {}), meta)

    def reference_detector(self) -> nn.Module:
        """The torch module ``detector.onnx`` computes (``BoxDetector``)."""
        return BoxDetector(self)

    def checkpoint(self, meta: dict) -> dict:
        """State, features, hidden size, NDVN head and metadata (``registry.save`` adds the kind)."""
        return {"state_dict": self.state_dict(), "features": list(self.features), "hidden": self.hidden,
                "ndvn_head": self.ndvn_head, "meta": meta}

    @classmethod
    def from_checkpoint(cls, ck: dict) -> BoxModel:
        """The model of a checkpoint dict (older checkpoints without a stored domain or NDVN rule get the defaults),
        in eval mode."""
        m = cls(ck["features"], ck["hidden"], ndvn_head=bool(ck.get("ndvn_head", False)))
        state = dict(ck["state_dict"])
        state.setdefault("domain", m.domain)  # checkpoints written before the domain was stored
        state.setdefault("ndvn_min", m.ndvn_min)  # and before the visible/NIR rule
        m.load_state_dict(state)
        return m.eval()

    @classmethod
    def from_training(cls, req: TrainRequest) -> tuple[BoxModel, dict, str]:
        """``torchskin train --method boxes|quantiles``: the model, its training summary and the one-line report
        (``train_on_dataset``)."""
        return train_on_dataset(req)

    def calibrate_to_budget(self, data: CalibrationData, scene_budget: float, pfa_budget: float,
                            iters: int = 30) -> dict:
        """``evaluation.calibrate_to_budget`` for boxes: the largest ``scale`` (every box shrunk about its centre),
        never above the current one, at which the bright non-skin rows inside their boxes are within
        ``scene_budget`` and the bright earthlib test spectra within ``pfa_budget`` in every configuration. Sets
        it and returns knob, before, after and pfa_scene."""
        start = float(self.scale)
        nonskin = data.nonskin

        def ok(scale: float) -> bool:
            self.scale.fill_(scale)
            with torch.no_grad():
                box = self(data.X)
                hit = inside_box(box, data.ndgri, data.ndsi, data.ndvn) & data.bright
                earth = float(false_alarm_rate(self(data.cfg_X), data.test_pts).max())
            return float(hit[nonskin].float().mean()) <= scene_budget and earth <= pfa_budget

        lo, hi = 0.0, start
        if ok(start):
            lo = start
        else:
            for _ in range(iters):
                mid = 0.5 * (lo + hi)
                lo, hi = (mid, hi) if ok(mid) else (lo, mid)
        ok(lo)
        with torch.no_grad():
            rate = float((inside_box(self(data.X), data.ndgri, data.ndsi, data.ndvn) & data.bright)[nonskin]
                         .float().mean())
        return {"knob": "scale", "before": start, "after": lo, "pfa_scene": rate}

    #: the model card's "Intended use" of this kind (``modelcard``)
    card_use: ClassVar[str] = (
        "Onboard skin detection in 4-band (544, 633, 1080, 1580 nm) reflectance imagery with the NDGRI/NDSI "
        "rules detector of the thesis (eq 2.5.10), the rules box chosen for the frame's sun and camera geometry "
        "instead of the fixed diffuse-model box, plus a visible/NIR rule NDVN = ((g + r) - (n + s)) / (g + r + "
        "n + s) >= d1 (box column 5) that keeps litter, bark and dry vegetation out where the box reaches down "
        "towards them.")

    @staticmethod
    def card_false_alarms(train: dict, f: Any) -> str:
        """The model card's account of the false-alarm tuning (``tune_false_alarms``) from the training summary
        ``train``, numbers formatted with ``f``."""
        return (f"the boxes were shrunk by {f(train.get('scale'))} so that at most {f(train.get('pfa_budget'))} of "
                f"the earthlib *train* spectra fall inside any box over {train.get('calibration_configs', 'n/a')} "
                f"configurations (worst case after calibration: {f(train.get('pfa_train_worst'))})")


@dataclass
class TrainResult:
    model: BoxModel
    loss: float
    rows: int


def _initial_model(X: torch.Tensor, Y: torch.Tensor, features: Sequence[str], hidden: int, q: float, seed: int,
                   domain: Any = None, ndvn_quantile: float | None = None) -> BoxModel:
    """A model that starts at the pooled (q, 1 - q) quantile box (and, with ``ndvn_quantile``, a learned d1 at
    the pooled NDVN quantile of ``Y[:, 2]`` less ``NDVN_MARGIN``), with small deterministic weights (``seed``)
    and the training ``domain`` ((k, 2); default: the extremes of ``X``)."""
    g = torch.Generator().manual_seed(seed)
    if domain is None:
        domain = torch.stack([X.min(0).values, X.max(0).values], -1)
    head = ndvn_quantile is not None
    model = BoxModel(features, hidden, X.mean(0), X.std(0).clamp_min(1e-6), domain, ndvn_head=head)
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


def train_boxes(X: torch.Tensor, Y: torch.Tensor, confusers: torch.Tensor, settings: BoxTraining | None = None, *,
                scene: tuple[torch.Tensor, torch.Tensor] | None = None, **options: Any) -> TrainResult:
    """Learn the box that, per configuration, covers the most sunlit skin pixels ``Y`` (n, 2) given their
    configuration features ``X`` (n, k), while every ``confusers`` point (m, 2) (the earthlib *train* spectra)
    stays ``margin`` outside it, for ``domain_configs`` training configurations and as many random
    configurations over the training domain per step::

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
    from 0.80 to 0.78: not kept; ``evaluation.calibrate_to_budget`` closes the gap on the held-out set.)
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
        the number of skin pixels.

    The settings are a ``BoxTraining`` (default: its defaults); keyword ``options`` (its field names, e.g.
    ``steps=800, margin=0.02``) change single fields, so ``train_boxes(X, Y, C, hidden=0)`` still works."""
    st = (settings or BoxTraining()).with_options(**options)
    features, hidden, steps, lr, tau, margin = st.features, st.hidden, st.steps, st.lr, st.tau, st.margin
    width_cost, fa_weight, domain_configs, batch, seed = st.width_cost, st.fa_weight, st.domain_configs, st.batch, st.seed
    domain, per_config, spread_cost, allow, ndvn_min = st.domain, st.per_config, st.spread_cost, st.allow, st.ndvn_min
    init_quantile, init_steps, scene_budget = st.init_quantile, st.init_steps, st.scene_budget
    scene_weight, ndvn_quantile = st.scene_weight, st.ndvn_quantile
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


METHODS = ("boxes", "quantiles")


def learn(X: torch.Tensor, Y: torch.Tensor, method: str = "boxes", pfa_budget: float = 1e-3,
          confusers: torch.Tensor | None = None, ndvn_quantile: float | None = NDVN_QUANTILE,
          scene: tuple[torch.Tensor, torch.Tensor] | None = None, scene_budget: float = 1e-4,
          **options: Any) -> tuple[BoxModel, dict]:
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

    Raises ``ValueError`` on a bad method or budget, and ``errors.Failure`` (a failure, not bad input: exit status
    1 on the command line) when the boxes hold less than ``MIN_TRAIN_COVERAGE`` of the training skin pixels. (No doctest: even a tiny run trains for seconds; see tests/test_boundaries_onnx.py.)
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
        raise Failure(f"training failed: the learned boxes hold only {coverage:.3f} of the training skin pixels "
                         f"(< {MIN_TRAIN_COVERAGE}); the optimisation left the data. Try another seed (--seed) or "
                         "fewer hidden units (--hidden), or check the dataset and the false-alarm budget")
    return res.model, {"method": method, "rows": res.rows, "loss": res.loss, "scale": scale,
                       "ndvn_min": d1_range[0], "ndvn_range": d1_range, "ndvn_learned": learned_d1,
                       "pfa_budget": pfa_budget, "pfa_train_worst": pfa_train, "train_coverage": coverage,
                       "scene_budget": scene_budget if scene is not None else None, "pfa_scene_train": pfa_scene,
                       "scene_pixels": int(scene[0].shape[0]) if scene is not None else 0,
                       # the key keeps its old name: checkpoints and model cards carry it
                       "calibration_configs": int(cfg.shape[0]), "options": options}


def save(model: BoxModel, path: str | os.PathLike, meta: dict | None = None) -> None:
    """A torch checkpoint (kind "boxes"): state, features and hidden size (+ metadata), written atomically through
    a buffer: the same model gives the same bytes."""
    write_checkpoint(model, path, meta)


def load(path: str | os.PathLike) -> BoxModel:
    """A ``BoxModel`` from a checkpoint written by ``save`` (those written before checkpoints carried a kind,
    and older ones without a stored domain or NDVN rule, included), in eval mode."""
    return BoxModel.from_checkpoint(torch.load(path, map_location="cpu", weights_only=True))


def train_on_dataset(req: TrainRequest) -> tuple[BoxModel, dict, str]:
    """``torchskin train --method boxes|quantiles`` on a dataset folder: the skin and scene rows
    (``load_skin_rows``, ``load_scene_rows``), the declared domain (``domain_from_manifest``), ``learn``; returns
    the model, its training summary (``learn``'s, with ``light_classes``) and the command's one-line report."""
    X, Y = load_skin_rows(req.data, sunlit_only=req.sunlit_only, frames=req.frames)
    scene = load_scene_rows(req.data, frames=req.frames) if req.use_scene else None
    opts: dict[str, Any] = {"hidden": req.hidden, "steps": req.steps, "seed": req.seed}
    domain = domain_from_manifest(req.data)
    own = {o.name: req.options.get(o.name, o.default) for o in BoxModel.options}
    if req.method == "quantiles":
        opts["q"] = own["q"]
    else:
        opts.update(margin=own["margin"], width_cost=own["width_cost"], spread_cost=own["spread_cost"])
    model, info = learn(X, Y, req.method, req.pfa_budget, domain=domain,
                        ndvn_quantile=NDVN_QUANTILE if own["ndvn_rule"] else None, scene=scene,
                        scene_budget=req.scene_budget, **opts)
    info["options"].pop("domain", None)
    info["light_classes"] = ["sunlit"] if req.sunlit_only else ["sunlit", "shadow"]
    info["frames"] = req.frames
    scene_text = "" if scene is None else (f"; scene non-skin {info['pfa_scene_train']:.2e} <= {req.scene_budget:g} "
                                           f"of {info['scene_pixels']} training pixels")
    text = (f"trained ({req.method}) on {info['rows']} {'sunlit ' if req.sunlit_only else ''}skin pixels, loss "
            f"{info['loss']:.5f}; NDVN rule d1 {info['ndvn_min']:.3f}; false-alarm scale {info['scale']:.3f}: worst "
            f"Pfa {info['pfa_train_worst']:.2e} <= {req.pfa_budget:g} on the earthlib train partition over "
            f"{info['calibration_configs']} configurations{scene_text}")
    return model, info, text


__all__ = ["METHODS", "BoxModel", "TrainResult", "learn", "load", "save", "train_boxes", "train_on_dataset",
           "train_quantiles"]
