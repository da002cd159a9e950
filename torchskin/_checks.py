"""Input validation helpers: clear ``ValueError`` messages naming the parameter and its allowed range."""

from __future__ import annotations

import torch


def as_tensor(x, like: torch.Tensor | None = None, dtype=None, device=None) -> torch.Tensor:
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


def check_range(name: str, x: torch.Tensor, lo: float, hi: float, unit: str = "") -> None:
    """Raise ``ValueError`` if any element of ``x`` is NaN or outside ``[lo, hi]``.

    One fused reduction; it synchronises with the device once (validation is not on a hot path).
    """
    if x.numel() == 0:
        return
    bad = torch.isnan(x) | (x < lo) | (x > hi)
    if bool(bad.any()):
        vals = x.detach()[bad]
        u = f" {unit}" if unit else ""
        raise ValueError(
            f"{name} must lie in [{lo:g}, {hi:g}]{u}; got {vals.min().item():g}..{vals.max().item():g}{u}"
            f" ({int(bad.sum())} of {x.numel()} values out of range or NaN)"
        )


def broadcast_shapes(**tensors: torch.Tensor) -> torch.Size:
    """``torch.broadcast_shapes`` with an error that names the offending parameters."""
    try:
        return torch.broadcast_shapes(*(t.shape for t in tensors.values()))
    except RuntimeError:
        desc = ", ".join(f"{k}{tuple(v.shape)}" for k, v in tensors.items())
        raise ValueError(f"shapes do not broadcast: {desc}") from None
