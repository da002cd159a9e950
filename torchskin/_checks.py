"""Input validation helpers: clear ``ValueError`` messages naming the parameter and its allowed range."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, TypeAlias

import numpy as np
import torch

#: what the public functions accept where they take numbers: a tensor, a Python number, or a (nested) sequence
#: of numbers or a numpy array (anything ``torch.as_tensor`` takes)
TensorLike: TypeAlias = torch.Tensor | float | Sequence[Any] | np.ndarray
#: a tensor or a Python number: what the formulas that compute on their inputs directly (no ``as_tensor``) take
Numeric: TypeAlias = torch.Tensor | float


def as_tensor(x: TensorLike, like: torch.Tensor | None = None, dtype: torch.dtype | None = None,
              device: torch.device | str | None = None) -> torch.Tensor:
    """Convert ``x`` to a floating tensor on ``like``'s device/dtype (or the given ones), keeping autograd."""
    if like is not None:
        dtype = dtype or like.dtype
        device = device or like.device
    if isinstance(x, torch.Tensor):
        t = x
        if dtype is not None and t.dtype != dtype:
            t = t.to(dtype)
        if device is not None and t.device != torch.device(device):
            t = t.to(device)
    else:
        t = torch.as_tensor(x, dtype=dtype, device=device)
    if not t.is_floating_point():
        t = t.to(torch.get_default_dtype())
    return t


def check_range(name: str, x: TensorLike, lo: float, hi: float, unit: str = "", *, lo_open: bool = False,
                hi_open: bool = False) -> None:
    """Raise ``ValueError`` if any element of ``x`` (a tensor or a Python number) is NaN or outside the
    interval from ``lo`` to ``hi`` (closed by default; ``lo_open``/``hi_open`` exclude an end, so
    ``hi=math.inf, hi_open=True`` also refuses infinities).

    One fused reduction; it synchronises with the device once (validation is not on a hot path).
    """
    if not isinstance(x, torch.Tensor):
        x = torch.as_tensor(x, dtype=torch.float64)
    if x.numel() == 0:
        return
    if not x.is_floating_point():
        x = x.to(torch.float64)
    bad = torch.isnan(x) | ((x <= lo) if lo_open else (x < lo)) | ((x >= hi) if hi_open else (x > hi))
    if bool(bad.any()):
        vals = x.detach()[bad]
        u = f" {unit}" if unit else ""
        iv = f"{'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
        raise ValueError(
            f"{name} must lie in {iv}{u}; got {vals.min().item():g}..{vals.max().item():g}{u}"
            f" ({int(bad.sum())} of {x.numel()} values out of range or NaN)"
        )


def broadcast_shapes(**tensors: torch.Tensor) -> torch.Size:
    """``torch.broadcast_shapes`` with an error that names the offending parameters."""
    try:
        return torch.broadcast_shapes(*(t.shape for t in tensors.values()))
    except RuntimeError:
        desc = ", ".join(f"{k}{tuple(v.shape)}" for k, v in tensors.items())
        raise ValueError(f"shapes do not broadcast: {desc}") from None
