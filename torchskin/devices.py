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
    """Where torch.compile (Inductor) keeps compiled kernels between runs: ``TORCHINDUCTOR_CACHE_DIR`` when the user
    sets it, else Inductor's own default (a ``torchinductor_<user>`` folder in the temporary directory). torchskin
    reads it and never sets it (it writes no environment variables). Kernels built under one CPU vector ISA and
    loaded under another computed garbage in this project's tests (torch 2.13's cache does not key CPU kernels on
    the ISA); compiled CPU kernels run only under ``COMPILED_CPU_CAPABILITIES``, so no other ISA loads them."""
    import os

    if os.environ.get("TORCHINDUCTOR_CACHE_DIR"):
        return os.path.abspath(os.environ["TORCHINDUCTOR_CACHE_DIR"])
    try:
        from torch._inductor.runtime.cache_dir_utils import default_cache_dir
    except ImportError:  # a torch without this module: its documented default
        import getpass
        import tempfile

        return os.path.join(tempfile.gettempdir(), f"torchinductor_{getpass.getuser()}")
    return os.path.abspath(default_cache_dir())


#: torch CPU capabilities whose Inductor kernels this project has validated (compiled = eager in every test).
#: Kernels compiled under one capability must never be loaded under another (``inductor_cache_dir``): widen this
#: only together with a cache folder per ISA. Under AVX2 (``ATEN_CPU_CAPABILITY=avx2`` on an AVX-512 machine,
#: torch 2.13) Inductor's kernels for the skin model and the renderer returned garbage (1e31, NaN) in every other
#: 8-float block after unrelated float64 work in the same process (an L-BFGS fit), with a cold or warm cache, one
#: thread or two: a wrong answer without an error. Until a torch release is shown free of it, other capabilities
#: run the eager kernels.
COMPILED_CPU_CAPABILITIES = ("AVX512",)


def compiler_problem(device: torch.device | str = "cpu") -> str | None:
    """Why ``torch.compile`` cannot be used for ``device`` here (None: it can): on the CPU a C++ compiler
    (``CXX``, else g++, c++ or clang++ on the PATH) and a validated CPU capability (``COMPILED_CPU_CAPABILITIES``);
    Triton on CUDA; MPS has Inductor's Metal backend.

    >>> compiler_problem("meta")
    "no torch.compile backend for 'meta' here"
    """
    import importlib.util
    import os
    import shutil

    kind = torch.device(device).type
    if kind == "cpu":
        names = [os.environ["CXX"]] if os.environ.get("CXX") else ["g++", "c++", "clang++"]
        if not any(shutil.which(n) for n in names):
            return "no C++ compiler (install g++)"
        cap = torch.backends.cpu.get_cpu_capability()
        if not cap.upper().startswith(COMPILED_CPU_CAPABILITIES):
            return (f"compiled CPU kernels are validated only for {', '.join(COMPILED_CPU_CAPABILITIES)}, torch runs "
                    f"{cap} here (torch 2.13's AVX2 kernels computed wrong values in this project's tests)")
        return None
    if kind == "cuda":
        return None if importlib.util.find_spec("triton") is not None else "no triton for CUDA"
    if kind == "mps":
        return None
    return f"no torch.compile backend for {kind!r} here"

