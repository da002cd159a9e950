"""The one cache of ``torch.compile``d kernels: the skin model's hot loop (``tissue``) and the renderer's per-pixel
stages (``render.kernels``) both take their compiled forms from ``KERNELS``.

A kernel is compiled lazily, once per (kernel name, device type), and falls back to the eager function, with one
``RuntimeWarning``, wherever it cannot run compiled: no compiler or an unvalidated CPU capability for the device
(``devices.compiler_problem``: one warning per device), or Inductor failing on a call (one warning per kernel).
The eager function is the reference: a fallback gives its results bit for bit.

torchskin writes no environment variable. Inductor keeps compiled kernels on disk between runs in its own cache
(``TORCHINDUCTOR_CACHE_DIR`` when the user sets it, else Inductor's default, which torch itself records in
that variable on its first compilation: ``devices.inductor_cache_dir``).

>>> cache = KernelCache()
>>> double = cache.get(lambda x: 2 * x, compile=False)
>>> int(double(torch.tensor(3))), len(cache)
(6, 0)
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable

import torch

from .devices import compiler_problem


def mark_dynamic(args: tuple) -> None:
    """Mark every axis longer than 16 of the tensor arguments dynamic (pixels, faces, rows of pixels), so that one
    compilation serves every frame size; shorter axes (components, bands, band tiles, suns) stay static, so that
    Inductor vectorises along them with known strides."""
    for a in args:
        if isinstance(a, dict):
            mark_dynamic(tuple(a.values()))
        elif isinstance(a, torch.Tensor):
            for d, size in enumerate(a.shape):
                if size > 16:
                    torch._dynamo.maybe_mark_dynamic(a, d)


def signature(a: object, dynamic: bool = True) -> tuple:
    """What decides whether a compiled function specialises anew: dtype, rank and sizes (with ``dynamic``, the
    static (short) axes' sizes only: see ``mark_dynamic``)."""
    if isinstance(a, torch.Tensor):
        return (a.dtype, a.device.type, a.dim(), tuple(s if (s <= 16 or not dynamic) else -1 for s in a.shape))
    if isinstance(a, (dict, list, tuple)):
        items = a.items() if isinstance(a, dict) else enumerate(a)
        return (type(a).__name__, *((k, signature(v, dynamic)) for k, v in items))
    if callable(a):
        return (type(a), id(a))
    return (type(a), a if isinstance(a, (bool, int, float, str)) or a is None else None)


class KernelCache:
    """Compiled forms of kernel functions, one per (kernel name, device type), and the wall time of each call
    that compiled (``compile_seconds``, by kernel name; a later shape that needs another specialisation adds
    to it). ``clear()`` drops them all; ``len()`` counts the compiled kernels held.

    ``get(fn, compile, device, name=None, dynamic=True)``: ``fn`` itself when ``compile`` is false or compiling
    is impossible for ``device`` (one warning per device), else a callable that runs ``fn`` compiled and falls
    back to ``fn`` (one warning per kernel) if Inductor fails. ``dynamic``: axes longer than 16 are marked
    dynamic at every call (``mark_dynamic``: one compilation serves every frame size); ``dynamic=False``
    compiles ``torch.compile(fn, dynamic=False)``, one specialisation per shape."""

    def __init__(self) -> None:
        self._compiled: dict[tuple[str, str], Callable] = {}
        self._signatures: set[tuple] = set()
        self._failed: set[tuple[str, str]] = set()
        self.compile_seconds: dict[str, float] = {}

    def clear(self) -> None:
        """Drop every compiled kernel and forget the fallbacks (they warn again on next use)."""
        self._compiled.clear()
        self._signatures.clear()
        self._failed.clear()
        self.compile_seconds.clear()

    def __len__(self) -> int:
        return len(self._compiled)

    def get(self, fn: Callable, compile: bool = True, device: torch.device | str = "cpu", *, name: str | None = None,
            dynamic: bool = True) -> Callable:
        """``fn`` compiled for ``device`` (lazily, on its first call) when ``compile``, else ``fn``; see the class."""
        kind = torch.device(device).type
        name = name or f"{getattr(fn, '__module__', '')}.{getattr(fn, '__qualname__', type(fn).__name__)}"
        key = (name, kind)
        if not compile or key in self._failed:
            return fn
        why = compiler_problem(kind)
        if why is not None:  # one warning per device, not per kernel
            self._fail(("compiled kernels", kind), why)
            return fn
        if key not in self._compiled:
            self._compiled[key] = torch.compile(fn, dynamic=False) if not dynamic else torch.compile(fn)
        compiled = self._compiled[key]
        label = getattr(fn, "__name__", name)

        def run(*args: object) -> object:
            if dynamic:
                mark_dynamic(args)
            sig = (key, *(signature(a, dynamic) for a in args))
            if sig in self._signatures:
                return compiled(*args)
            t0 = time.perf_counter()
            try:
                out = compiled(*args)
            except Exception as e:  # noqa: BLE001 - any compiler failure falls back to the eager reference
                self._fail(key, f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}")
                self._compiled.pop(key, None)
                return fn(*args)
            self._signatures.add(sig)
            self.compile_seconds[label] = self.compile_seconds.get(label, 0.0) + time.perf_counter() - t0
            return out

        return run

    def _fail(self, key: tuple[str, str], why: str) -> None:
        if key not in self._failed:
            self._failed.add(key)
            warnings.warn(f"running {key[0]} eagerly on {key[1]}: {why}", RuntimeWarning, stacklevel=4)


#: the process-wide compiled kernels of the skin model and the renderer (``clear()`` to compile again)
KERNELS = KernelCache()
