"""Devices named on the command line (``--device``): check them before any work, with a message that says which
devices this machine has."""

from __future__ import annotations

import torch


def available_devices() -> list[str]:
    """The torch devices this machine can use.

    Returns:
        "cpu", then "cuda:0", "cuda:1".. and "mps" when present.

    >>> available_devices()[0]
    'cpu'
    """
    out = ["cpu"]
    if torch.cuda.is_available():
        out += [f"cuda:{i}" for i in range(torch.cuda.device_count())]
    mps = getattr(torch.backends, "mps", None)
    if mps is not None and mps.is_available():
        out.append("mps")
    return out


def check_device(name: str | torch.device, option: str = "--device") -> torch.device:
    """The device ``name`` names, checked to exist on this machine before any work.

    Args:
        name: a device name ("cpu", "cuda", "cuda:1", "mps") or a ``torch.device``; a bare "cuda" means "cuda:0".
        option: the command-line option that named it, for the message.

    Returns:
        ``torch.device(name)``; ``ValueError`` naming ``option`` and the devices that exist when this machine
        lacks it or ``name`` is not a device name.

    >>> check_device("cpu")
    device(type='cpu')
    """
    have = available_devices()
    try:
        dev = torch.device(str(name))
    except (RuntimeError, ValueError):
        raise ValueError(f"{option} {name!r} is not a device name; this machine has {', '.join(have)}") from None
    if dev.type == "cpu":
        return dev
    label = f"{dev.type}:{dev.index or 0}" if dev.type == "cuda" else dev.type
    if label not in have:
        raise ValueError(f"{option} {name!r} is not available on this machine; it has {', '.join(have)}")
    return dev


__all__ = ["available_devices", "check_device"]


def inductor_cache_dir() -> str:
    """Where torch.compile (Inductor) keeps compiled kernels between runs: ``TORCHINDUCTOR_CACHE_DIR`` when set,
    else ``~/.cache/torchskin/inductor/<torch version>-<CPU capability>`` (``XDG_CACHE_HOME`` honoured). One folder
    per CPU capability: torch 2.13's cache does not key its CPU kernels on the vector ISA, and kernels built for
    AVX-512 and loaded under ``ATEN_CPU_CAPABILITY=avx2`` computed garbage (NaN, 1e31) in this project's tests."""
    import os
    from pathlib import Path

    if os.environ.get("TORCHINDUCTOR_CACHE_DIR"):
        return os.environ["TORCHINDUCTOR_CACHE_DIR"]
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "torchskin" / "inductor"
    return str(base / f"{torch.__version__}-{torch.backends.cpu.get_cpu_capability()}")


def use_inductor_cache() -> None:
    """Point Inductor at ``inductor_cache_dir()`` before a first ``torch.compile`` (it reads the variable when it
    first compiles)."""
    import os

    os.environ.setdefault("TORCHINDUCTOR_CACHE_DIR", inductor_cache_dir())

