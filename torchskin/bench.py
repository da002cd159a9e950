"""Benchmark harness behind ``torchskin bench``: each entry returns a JSON-ready dict.

Figures are medians of repeated runs after a warm-up; compare ratios measured in one run, not absolute
times across machines.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable

import torch

from . import tissue


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    elif device.type == "mps":
        torch.mps.synchronize()


def _median_seconds(fn: Callable[[], object], device: torch.device, repeat: int, warmup: int = 1) -> float:
    for _ in range(warmup):
        fn()
    _sync(device)
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        _sync(device)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def km_throughput(
    device: str | torch.device = "cpu",
    dtype: torch.dtype = torch.float32,
    n_skins: int = 100_000,
    n_wavelengths: int = 64,
    repeat: int = 5,
    compile: bool = False,
) -> dict:
    """Skin x wavelength evaluations per second of the full model (nine layers, substrate, surface)."""
    device = torch.device(device)
    skins, _ = tissue.sample(n_skins, 0, dtype=dtype, device=device)
    wl = torch.linspace(400.0, 1690.0, n_wavelengths, dtype=dtype, device=device)

    def run():
        with torch.no_grad():
            return tissue.total_reflectance(skins, wl, compile=compile)

    sec = _median_seconds(run, device, repeat, warmup=2 if compile else 1)
    return {
        "samples_x_bands_per_s": n_skins * n_wavelengths / sec,
        "seconds": sec,
        "skins": n_skins,
        "wavelengths": n_wavelengths,
        "device": str(device),
        "dtype": str(dtype).replace("torch.", ""),
        "compiled": compile,
        "threads": torch.get_num_threads(),
    }


def bench_km(compile: bool = False) -> dict:
    out = {"km": km_throughput("cpu")}
    if compile:
        out["km_compiled"] = km_throughput("cpu", compile=True)
    if torch.cuda.is_available():
        out["km_cuda"] = km_throughput("cuda", n_skins=1_000_000)
    if getattr(torch.backends, "mps", None) is not None and torch.backends.mps.is_available():
        out["km_mps"] = km_throughput("mps", n_skins=1_000_000)
    return out


#: name -> callable(**options) returning a dict of results (later issues add entries)
BENCHMARKS: dict[str, Callable[..., dict]] = {"km": bench_km}


def run(only: list[str] | None = None, compile: bool = False) -> dict:
    names = list(BENCHMARKS) if not only else only
    unknown = [n for n in names if n not in BENCHMARKS]
    if unknown:
        raise ValueError(f"unknown benchmark(s) {unknown}; available: {', '.join(BENCHMARKS)}")
    results: dict = {}
    for n in names:
        results.update(BENCHMARKS[n](compile=compile))
    return results
