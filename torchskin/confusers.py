"""Confuser spectra from the earthlib spectral library (MIT licence): 7,261 measured spectra, 400-2450 nm,
of soils, vegetation, roads, paint, roofing, concrete, metal... read from the package's own ENVI library
(no network), split by spectrum name into a fixed train / test partition.

The partition is a pure function of the name: SHA-256(name) decides, 80 % train, 20 % test. Train
detectors on the train part only and report false alarms on the test part.
"""

from __future__ import annotations

import functools
import hashlib
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from ._checks import as_tensor, check_range

TEST_FRACTION = 0.2


def partition(name: str) -> str:
    """'train' or 'test' for a spectrum name (fixed: the first 8 bytes of SHA-256(name) as a fraction)."""
    h = int.from_bytes(hashlib.sha256(name.encode("utf-8")).digest()[:8], "big") / 2.0**64
    return "test" if h < TEST_FRACTION else "train"


@functools.lru_cache(maxsize=1)
def _library():
    import earthlib  # the dataset extra: a ModuleNotFoundError names it (errors.missing_extra)
    root = Path(earthlib.__file__).parent / "data"
    hdr = (root / "spectra.sli.hdr").read_text()
    fields = {}
    for key in ("samples", "lines", "data type", "byte order"):
        line = next(ln for ln in hdr.splitlines() if ln.strip().startswith(key))
        fields[key] = int(line.split("=")[1])
    if fields["data type"] != 4:
        raise ValueError(f"unexpected earthlib library data type {fields['data type']} (expected float32)")
    wl_text = hdr.split("wavelength =", 1)[1].split("{", 1)[1].split("}", 1)[0]
    wl_nm = np.array([float(x) for x in wl_text.split(",")]) * (1000.0 if "Micrometers" in hdr else 1.0)
    dtype = "<f4" if fields["byte order"] == 0 else ">f4"
    data = np.fromfile(root / "spectra.sli", dtype=dtype).reshape(fields["lines"], fields["samples"])
    import csv

    with open(root / "spectra.csv", newline="", encoding="utf-8") as fh:
        meta = list(csv.DictReader(fh))
    if len(meta) != fields["lines"]:
        raise ValueError("earthlib metadata and library disagree on the number of spectra")
    names = [m["NAME"] for m in meta]
    classes = [f"{m['LEVEL_1']}/{m['LEVEL_2']}/{m['LEVEL_3']}" for m in meta]
    parts = np.array([partition(n) for n in names])
    return names, classes, wl_nm.astype(np.float64), data.astype(np.float64), parts


def library(part: str | None = None) -> tuple[list[str], list[str], np.ndarray, np.ndarray]:
    """``(names, classes, wavelengths_nm (K,), reflectance (N, K))`` of the whole library or of one
    partition ("train" / "test")."""
    if part is not None and part not in ("train", "test"):
        raise ValueError(f"partition must be 'train' or 'test', got {part!r}")
    names, classes, wl, R = _partition(part)
    return list(names), list(classes), wl, R


@functools.lru_cache(maxsize=4)
def _partition(part: str | None) -> tuple[tuple[str, ...], tuple[str, ...], np.ndarray, np.ndarray]:
    """``library(part)``, computed once per partition (read-only arrays)."""
    names, classes, wl, R, parts = _library()
    sel = np.arange(len(names)) if part is None else np.nonzero(parts == part)[0]
    R = R[sel]
    R.flags.writeable = False
    return tuple(names[i] for i in sel), tuple(classes[i] for i in sel), wl, R


def band_reflectance(wavelengths_nm: Sequence[float] | torch.Tensor,
                     part: str | None = None) -> tuple[list[str], torch.Tensor]:
    """Names and reflectance (N, B) of the library's spectra at band centres (linear interpolation),
    clipped to [0, 1]."""
    names, _, wl, R = library(part)
    w = as_tensor(wavelengths_nm, dtype=torch.float64)
    check_range("wavelengths (earthlib)", w, float(wl[0]), float(wl[-1]), "nm")
    out = np.stack([np.interp(w.numpy(), wl, r) for r in R]) if len(R) else np.zeros((0, w.numel()))
    return names, torch.from_numpy(np.clip(out, 0.0, 1.0))


def spectrum(name: str, wavelengths_nm: Sequence[float]) -> list[float]:
    """One named spectrum at the given wavelengths (clipped to [0, 1])."""
    _, _, wl, R = _partition(None)
    i = _name_index().get(name)
    if i is None:
        raise ValueError(f"no earthlib spectrum named {name!r}")
    return np.clip(np.interp(np.asarray(wavelengths_nm, dtype=float), wl, R[i]), 0.0, 1.0).tolist()


#: earthlib families (class prefixes) that stand in for clothing: built materials (paint, roofing, tile, metal,
#: concrete, ...) for dyed and synthetic fabrics, non-photosynthetic vegetation (bark, litter, wood, dry plant
#: matter) for natural ones. The library holds no fabric spectra; these are its closest measured stand-ins.
CLOTHING_FAMILIES = ("impervious/built/", "pervious/npv/")


def family(name: str) -> str:
    """The earthlib class (LEVEL_1/LEVEL_2/LEVEL_3, e.g. "impervious/built/paint") of a spectrum name."""
    names, classes, _, _ = library()
    index = _name_index()
    if name not in index:
        raise ValueError(f"no earthlib spectrum named {name!r}")
    return classes[index[name]]


@functools.lru_cache(maxsize=1)
def _name_index() -> dict[str, int]:
    return {n: i for i, n in enumerate(library()[0])}


@functools.lru_cache(maxsize=2)
def clothing_library(part: str) -> tuple[str, ...]:
    """Names of the spectra of partition ``part`` whose class is one of ``CLOTHING_FAMILIES``."""
    names, classes, _, _ = library(part)
    return tuple(n for n, c in zip(names, classes) if c.startswith(CLOTHING_FAMILIES))
