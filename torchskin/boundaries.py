"""Configuration-dependent rules-detector boundaries: configuration features -> box (b1, b2, c1, c2) on
(NDGRI, NDSI), learned as conditional quantiles of sunlit skin pixels (pinball loss) from generated datasets.

The model is a small MLP on standardised features with an output that keeps b1 <= b2 and c1 <= c2:
    (lo_g, w_g, lo_s, w_s) -> b1 = lo_g, b2 = lo_g + softplus(w_g), c1 = lo_s, c2 = lo_s + softplus(w_s).
It is exported to ONNX (``torchskin.export``) and run onboard without torch (``torchskin.onboard``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

#: default configuration features (what an onboard computer knows: sun position and camera pointing)
FEATURES = ("sun_zenith_deg", "camera_zenith_deg", "relative_azimuth_deg")
FEATURE_UNITS = {"sun_zenith_deg": "deg", "camera_zenith_deg": "deg", "relative_azimuth_deg": "deg",
                 "range_m": "m"}
#: training domain of each feature (inputs outside it are flagged onboard)
FEATURE_DOMAIN = {"sun_zenith_deg": (0.0, 90.0), "camera_zenith_deg": (0.0, 90.0),
                  "relative_azimuth_deg": (0.0, 180.0), "range_m": (0.0, 10000.0)}


class BoundaryModel(nn.Module):
    """Configuration features (N, k) -> boxes (N, 4) = (b1, b2, c1, c2)."""

    def __init__(self, features=FEATURES, hidden: int = 32, mean=None, std=None):
        super().__init__()
        self.features = tuple(features)
        k = len(self.features)
        self.register_buffer("mean", torch.zeros(k) if mean is None else torch.as_tensor(mean, dtype=torch.float32))
        self.register_buffer("std", torch.ones(k) if std is None else torch.as_tensor(std, dtype=torch.float32))
        self.register_buffer("scale", torch.ones(()))  # false-alarm calibration: box half-widths x scale
        self.net = nn.Sequential(nn.Linear(k, hidden), nn.Tanh(), nn.Linear(hidden, hidden), nn.Tanh(),
                                 nn.Linear(hidden, 4))

    def forward(self, config: torch.Tensor) -> torch.Tensor:
        z = self.net((config - self.mean) / self.std)
        lo_g, w_g, lo_s, w_s = z.unbind(-1)
        hg, hs = 0.5 * self.scale * nn.functional.softplus(w_g), 0.5 * self.scale * nn.functional.softplus(w_s)
        mg, ms = lo_g + 0.5 * nn.functional.softplus(w_g), lo_s + 0.5 * nn.functional.softplus(w_s)
        return torch.stack([mg - hg, mg + hg, ms - hs, ms + hs], -1)


def pinball(pred: torch.Tensor, target: torch.Tensor, q: float) -> torch.Tensor:
    """Quantile (pinball) loss: mean of max(q e, (q - 1) e), e = target - pred."""
    e = target - pred
    return torch.maximum(q * e, (q - 1) * e).mean()


@dataclass
class TrainResult:
    model: BoundaryModel
    loss: float
    rows: int


def load_skin_rows(data_dir, features=FEATURES, sunlit_only: bool = True):
    """Features (n, k) and (NDGRI, NDSI) (n, 2) of the skin pixels of a generated dataset (float32)."""
    import pyarrow.dataset as ds

    cols = list(features) + ["ndgri", "ndsi", "label", "shadow"]
    t = ds.dataset(str(data_dir), format="parquet").to_table(columns=cols)
    label = t.column("label").to_numpy(zero_copy_only=False)
    keep = label & (~t.column("shadow").to_numpy(zero_copy_only=False) if sunlit_only else True)
    X = np.stack([t.column(f).to_numpy(zero_copy_only=False) for f in features], -1)[keep]
    Y = np.stack([t.column("ndgri").to_numpy(zero_copy_only=False),
                  t.column("ndsi").to_numpy(zero_copy_only=False)], -1)[keep]
    ok = np.isfinite(X).all(1) & np.isfinite(Y).all(1)
    if not ok.any():
        raise ValueError(f"no usable sunlit skin pixels in {str(data_dir)!r}")
    return torch.from_numpy(X[ok].astype(np.float32)), torch.from_numpy(Y[ok].astype(np.float32))


def train_quantiles(X: torch.Tensor, Y: torch.Tensor, q: float = 0.01, features=FEATURES, hidden: int = 32,
                    steps: int = 2000, lr: float = 3e-3, seed: int = 0) -> TrainResult:
    """Fit the box as conditional quantiles: b1, c1 at ``q`` and b2, c2 at ``1 - q`` of sunlit skin NDGRI and
    NDSI given the configuration features (full-batch Adam on the pinball loss; deterministic in ``seed``)."""
    if not (0.0 < q < 0.5):
        raise ValueError(f"q must lie in (0, 0.5), got {q}")
    if X.shape[0] != Y.shape[0] or X.shape[1] != len(features) or Y.shape[1] != 2:
        raise ValueError(f"X (n, {len(features)}) and Y (n, 2) expected, got {tuple(X.shape)} and {tuple(Y.shape)}")
    g = torch.Generator().manual_seed(seed)
    model = BoundaryModel(features, hidden, X.mean(0), X.std(0).clamp_min(1e-6))
    with torch.no_grad():  # deterministic init, then start at the pooled quantiles
        for p in model.net.parameters():
            p.copy_(torch.randn(p.shape, generator=g) * (0.3 / math.sqrt(max(p.shape[-1], 1))))
        last = model.net[-1]
        last.weight.mul_(0.1)
        qg = torch.quantile(Y[:, 0], torch.tensor([q, 1 - q]))
        qs = torch.quantile(Y[:, 1], torch.tensor([q, 1 - q]))
        inv_sp = lambda w: torch.log(torch.expm1(w.clamp_min(1e-3)))  # noqa: E731
        last.bias.copy_(torch.stack([qg[0], inv_sp(qg[1] - qg[0]), qs[0], inv_sp(qs[1] - qs[0])]))
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    loss = torch.tensor(0.0)
    for _ in range(steps):
        opt.zero_grad()
        box = model(X)
        loss = (pinball(box[:, 0], Y[:, 0], q) + pinball(box[:, 1], Y[:, 0], 1 - q)
                + pinball(box[:, 2], Y[:, 1], q) + pinball(box[:, 3], Y[:, 1], 1 - q))
        loss.backward()
        opt.step()
    return TrainResult(model.eval(), float(loss.detach()), X.shape[0])


def save(model: BoundaryModel, path, meta: dict | None = None) -> None:
    """A torch checkpoint: state, features and hidden size (+ metadata)."""
    from .io import atomic_path

    with atomic_path(path, suffix=".pt") as tmp:
        torch.save({"state_dict": model.state_dict(), "features": list(model.features),
                    "hidden": model.net[0].out_features, "meta": meta or {}}, tmp)


def load(path) -> BoundaryModel:
    ck = torch.load(path, map_location="cpu", weights_only=True)
    m = BoundaryModel(ck["features"], ck["hidden"])
    m.load_state_dict(ck["state_dict"])
    return m.eval()


def confuser_indices(part: str = "train") -> torch.Tensor:
    """(NDGRI, NDSI) of the earthlib spectra of one partition, (n, 2): geometry-independent (Lambertian)."""
    from .confusers import band_reflectance
    from .detect import indices

    _, R = band_reflectance([544.0, 633.0, 1080.0, 1580.0], part)
    g, s = indices(R.float())
    return torch.stack([g, s], -1)


def false_alarm_rate(boxes: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Per box (N, 4): the fraction of ``points`` (n, 2) inside it."""
    g, s = points[:, 0][None], points[:, 1][None]
    b = boxes[:, :, None]
    inside = (g >= b[:, 0]) & (g <= b[:, 1]) & (s >= b[:, 2]) & (s <= b[:, 3])
    return inside.float().mean(-1)


def calibrate_false_alarms(model: BoundaryModel, configs: torch.Tensor, points: torch.Tensor,
                           budget: float = 1e-3, iters: int = 30) -> float:
    """Shrink every box about its centre (one global scale, found by bisection) until the false-alarm rate on
    ``points`` (the earthlib *train* partition) is within ``budget`` for every configuration in ``configs``.
    Sets and returns ``model.scale``."""
    def worst(scale):
        model.scale.fill_(scale)
        with torch.no_grad():
            return float(false_alarm_rate(model(configs), points).max())

    if worst(1.0) <= budget:
        return 1.0
    lo, hi = 0.0, 1.0
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if worst(mid) <= budget else (lo, mid)
    worst(lo)
    return lo
