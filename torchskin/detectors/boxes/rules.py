"""The ``boxes`` kind's rules: the visible/NIR rule's d1 (``ndvn_rule``), and what a box is for every box kind
(``protocol``'s ``BOX_ORDER``, ``inside_box`` and ``false_alarm_rate``, imported here for the kind's modules).
Imports no other part of the kind."""

from __future__ import annotations

import torch

from ..protocol import BOX_ORDER, false_alarm_rate, inside_box

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


__all__ = ["BOX_ORDER", "NDVN_MARGIN", "NDVN_QUANTILE", "false_alarm_rate", "inside_box", "ndvn_rule"]
