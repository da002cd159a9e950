"""The ``boxes`` kind's rules: the columns of a box (``BOX_ORDER``), the visible/NIR rule's d1 (``ndvn_rule``),
the rules detector with a box per configuration (``inside_box``) and the share of points a box holds
(``false_alarm_rate``). Imports no other part of the kind."""

from __future__ import annotations

import torch

from ...detect import rules_detector

#: the columns of a box: NDGRI min, NDGRI max, NDSI min, NDSI max, NDVN min
BOX_ORDER = ("b1_ndgri_min", "b2_ndgri_max", "c1_ndsi_min", "c2_ndsi_max", "d1_ndvn_min")
#: ``ndvn_rule``: d1 = this quantile of the training skin's NDVN minus ``NDVN_MARGIN``
NDVN_QUANTILE = 0.01
NDVN_MARGIN = 0.05


def ndvn_rule(v: torch.Tensor, quantile: float | None = NDVN_QUANTILE, margin: float = NDVN_MARGIN) -> float:
    """d1 of the visible/NIR rule from the NDVN of training skin pixels ``v``: its ``quantile`` less ``margin``
    (-1, the rule off, when ``quantile`` is None)."""
    if quantile is None:
        return -1.0
    v = v[torch.isfinite(v)]
    if v.numel() == 0:
        return -1.0
    return max(-1.0, float(torch.quantile(v.double(), quantile)) - margin)


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


__all__ = ["BOX_ORDER", "NDVN_MARGIN", "NDVN_QUANTILE", "false_alarm_rate", "inside_box", "ndvn_rule"]
