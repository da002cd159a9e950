"""A figure of a ``lut`` model's decision region: slices of its table in the (NDGRI, NDSI) plane at a few
configurations, with a dataset's sunlit skin over them, coloured by local incidence angle θi.

>>> # region_plot(LookupKind.load("exports/lut.pt"), "out/pipeline/test", "exports/lut_region.png")
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np
import torch

from .model import LookupModel

#: the configurations shown: (sun zenith, camera zenith, relative azimuth) in degrees, and their titles
CONFIGS = (((20.0, 20.0, 30.0), "high sun, sun behind the camera"),
           ((50.0, 40.0, 30.0), "sun 50°, camera 40°"),
           ((70.0, 30.0, 30.0), "low sun (70°)"),
           ((45.0, 30.0, 150.0), "back-lit (azimuth 150°)"))


def region_plot(model: LookupModel, data_dir: str | os.PathLike, out: str | os.PathLike,
                configs: Sequence = CONFIGS) -> None:
    """Write ``out`` (PNG): for each configuration, the share of the table's other cells (the 633 / 1080 nm ratio
    and the brightness) that are skin at each cell of the 544 / 633 nm and 1080 / 1580 nm ratios, drawn in the
    (NDGRI, NDSI) plane (grey: the region seen from the plane), and the dataset's sunlit skin pixels
    of that table slice (``elm_valid`` frames) coloured by θi; the thesis's static box for scale."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ...bands import ratio_pairs
    from ...dataset.files import read_rows
    from ...detect import DEFAULT_BOX, ratio_indices
    from ...io import atomic_path
    from ..features import BAND_COLUMNS, FEATURES, feature_columns, stack_features
    from .grid import OCTAVE
    rows = read_rows(data_dir, [*feature_columns(model.features), *BAND_COLUMNS, "label", "shadow", "theta_i_deg"],
                     "physical")
    R = torch.from_numpy(rows.bands(np.float32))
    X = torch.from_numpy(stack_features(rows, model.features))
    lit = torch.from_numpy(rows["label"].astype(bool) & ~rows["shadow"].astype(bool))
    slices = model.slices(X)
    U = torch.stack(ratio_indices(R)[:2], 1)  # NDGRI, NDSI
    theta = rows["theta_i_deg"]
    b = model.bins
    band, towards = ratio_pairs(model.n_bands, model.ref)
    # the table's axes of the 544 / 633 nm and 1080 / 1580 nm ratios, each cell edge as a normalized difference
    # (at its nominal log2 ratio: the bits' piecewise-linear log2 is within 0.09 octave of it)
    plane, edges, flip = [], [], []
    for pair in ((0, 1), (2, 3)):
        k = next(k for k in range(1, model.n_bands) if {band[k], towards[k]} == set(pair))
        sign = 1.0 if band[k] < towards[k] else -1.0  # log2 of the shorter band's over the longer's
        d = sign * (float(model.lo[k]) + torch.arange(b + 1, dtype=torch.float64)) * 2.0 ** int(model.shift[k]) / OCTAVE
        e = ((2 ** d - 1) / (2 ** d + 1)).numpy()
        plane.append(k)
        flip.append(sign < 0)
        edges.append(e[::-1].copy() if sign < 0 else e)
    fig, axes = plt.subplots(1, len(configs), figsize=(3.6 * len(configs) + 1, 4.4), sharey=True,
                             layout="constrained")
    sc = None
    for ax, (cfg, title) in zip(np.atleast_1d(axes), configs):
        s = _slice_of(model, cfg, X, slices, FEATURES)
        grid = (model.levels[s] >= model.threshold.to(torch.uint8)).reshape((b,) * model.n_bands).float()
        rest = [k for k in range(model.n_bands) if k not in plane]
        on = grid.permute(*plane, *rest).reshape(b, b, -1).mean(-1)
        for axis, f in enumerate(flip):
            on = on.flip(axis) if f else on
        ax.pcolormesh(edges[0], edges[1], on.T.numpy(), cmap="Greys", vmin=0, vmax=0.5, shading="flat")
        m = (lit & (slices == s)).numpy()
        hit = model.decide(R[m], X[m]).numpy() if m.any() else np.zeros(0, dtype=bool)
        if m.any():
            sc = ax.scatter(U[m, 0], U[m, 1], c=theta[m], s=2, cmap="viridis", vmin=0, vmax=90, alpha=0.5,
                            rasterized=True)
        box = DEFAULT_BOX
        ax.add_patch(plt.Rectangle((box.b1, box.c1), box.b2 - box.b1, box.c2 - box.c1, fill=False, color="tab:red",
                                   lw=1.2, label="static box (thesis)"))
        kept = f"; kept {hit.mean():.3f} of {m.sum()}" if m.any() else "; no sunlit skin in this slice"
        ax.set_title(f"{title}{_other_bins(model, s, FEATURES)}\nslice {s}{kept}", fontsize=9)
        ax.set_xlabel("NDGRI (544, 633 nm)")
        ax.set_xlim(edges[0][0], edges[0][-1])
        ax.set_ylim(edges[1][0], edges[1][-1])
    np.atleast_1d(axes)[0].set_ylabel("NDSI (1080, 1580 nm)")
    np.atleast_1d(axes)[0].legend(loc="lower left", fontsize=8)
    if sc is not None:
        fig.colorbar(sc, ax=axes, shrink=0.85, label="sunlit skin: local incidence θi (deg)")
    fig.suptitle("The lookup table's region seen from the index plane (grey: share of its other two axes' cells "
                 "that are skin: 633 / 1080 nm and brightness) and the test set's sunlit skin", fontsize=10)
    with atomic_path(out) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)


def _other_bins(model: LookupModel, s: int, angles: Sequence[str]) -> str:
    """The ranges of slice ``s``'s bins of the features other than the angles, as text (", diffuse share
    0.00-0.25"), "" for a model of the angles alone."""
    bins = np.unravel_index(s, model.config_counts)
    out = []
    for j, f in enumerate(model.features):
        if f not in angles:
            lo = float(model.cfg_lo[j]) + bins[j] / float(model.cfg_inv[j])
            out.append(f"{f.replace('_', ' ')} {lo:.2f}-{lo + 1 / float(model.cfg_inv[j]):.2f}")
    return "".join(", " + t for t in out)


def _slice_of(model: LookupModel, cfg: Sequence[float], X: torch.Tensor, slices: torch.Tensor,
              angles: Sequence[str]) -> int:
    """The table slice of the angles ``cfg`` (sun zenith, camera zenith, relative azimuth). A model that also takes
    other features (the diffuse share) shows the slice that most of the dataset's rows (``X``, in ``slices``) at
    those angles fall in; with no such row, the other features at 0."""
    pos = [model.features.index(f) for f in angles]
    probe = torch.zeros(1, len(model.features))
    probe[0, pos] = torch.tensor([float(v) for v in cfg])
    if len(model.features) == len(angles):
        return int(model.slices(probe)[0])
    same = torch.ones(len(X), dtype=torch.bool)
    for j, v in zip(pos, cfg):
        moved = X.clone()
        moved[:, j] = float(v)  # a row keeps its slice iff it lies in this angle's bin
        same &= model.slices(moved) == slices
    return int(torch.mode(slices[same]).values) if same.any() else int(model.slices(probe)[0])


__all__ = ["CONFIGS", "region_plot"]
