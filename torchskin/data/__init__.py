"""Packaged spectral tables and loaders returning tensors on any wavelength grid.

Every loader takes ``wavelengths`` in nm (any shape; the result has the same shape, device and dtype) and
raises ``ValueError`` when a wavelength lies outside the table. Sources and citations: ``README.md`` in
this folder.
"""

from __future__ import annotations

import functools
from importlib import resources

import numpy as np
import torch

from .._checks import TensorLike, as_tensor, check_range

LN10 = float(np.log(10.0))
HB_GRAMS_PER_LITRE = 150.0  # hemoglobin concentration of whole blood (Prahl's convention)
HB_MOLAR_MASS = 64500.0  # g/mol

_TABLES: dict[str, np.ndarray] = {}
_COLUMNS: dict[str, tuple[str, ...]] = {}
_tables_version = 0


def tables_version() -> int:
    """The version of the table registry: it starts at 0 and every ``register_table`` or ``unregister_table``
    increments it. Anything computed from the tables and kept (a cache) must be keyed on it, so that it is
    never served from a replaced table.

    >>> v = tables_version()
    >>> register_table("my_table", [400.0, 1700.0], [1.0, 2.0]); unregister_table("my_table")
    >>> tables_version() - v
    2
    """
    return _tables_version


def _tables_changed() -> None:
    global _tables_version
    _tables_version += 1


def register_table(name: str, wavelengths_nm: TensorLike, values: TensorLike) -> None:
    """Register (or replace) a one-column table ``name`` so loaders use it instead of the packaged file.

    ``values`` must be in the units of the table it replaces (see ``README.md``). Increments
    ``tables_version()``; ``unregister_table`` restores the packaged table.
    """
    w = np.asarray(wavelengths_nm, dtype=np.float64)
    v = np.asarray(values, dtype=np.float64)
    if w.ndim != 1 or v.shape != w.shape or w.size < 2:
        raise ValueError("wavelengths_nm and values must be 1-D arrays of equal length >= 2")
    if np.any(np.diff(w) <= 0):
        raise ValueError("wavelengths_nm must be strictly increasing")
    _TABLES[name] = np.stack([w, v], axis=1)
    _COLUMNS[name] = ("wavelength_nm", "value")
    _tables_changed()


def unregister_table(name: str) -> None:
    """Remove the table ``register_table`` registered as ``name``: loaders use the packaged file again.
    Increments ``tables_version()``; ``ValueError`` if no table of that name is registered."""
    if name not in _TABLES:
        raise ValueError(f"no registered table {name!r}; registered: {', '.join(sorted(_TABLES)) or 'none'}")
    del _TABLES[name], _COLUMNS[name]
    _tables_changed()


@functools.cache
def _read_csv(filename: str) -> tuple[tuple[str, ...], np.ndarray]:
    with resources.files(__name__).joinpath(filename).open("r", encoding="utf-8") as fh:
        header = fh.readline().strip().split(",")
        data = np.loadtxt(fh, delimiter=",", ndmin=2)
    order = np.argsort(data[:, 0], kind="stable")
    return tuple(header), data[order]


def table(name: str) -> tuple[tuple[str, ...], np.ndarray]:
    """Return ``(column_names, array)`` of a packaged table (file name without ``.csv``)."""
    if name in _TABLES:
        return _COLUMNS[name], _TABLES[name]
    try:
        return _read_csv(name + ".csv")
    except FileNotFoundError:
        raise ValueError(f"unknown table {name!r}; available: {', '.join(available_tables())}") from None


def available_tables() -> list[str]:
    """Names of the packaged tables (file names without ``.csv``)."""
    return sorted(p.name[:-4] for p in resources.files(__name__).iterdir() if p.name.endswith(".csv"))


def interp(x: torch.Tensor, xp: torch.Tensor, fp: torch.Tensor) -> torch.Tensor:
    """Piecewise-linear interpolation of ``fp(xp)`` at ``x`` (``xp`` increasing), on ``x``'s device.

    ``fp`` may carry leading batch axes: ``fp`` (..., K) gives ``(..., *x.shape)``. No range check here.
    """
    xp = xp.contiguous()
    idx = torch.searchsorted(xp, x.detach().contiguous(), right=True).clamp(1, xp.numel() - 1)
    x0, x1 = xp[idx - 1], xp[idx]
    t = (x - x0) / (x1 - x0)
    f0, f1 = fp[..., idx - 1], fp[..., idx]
    return f0 + t * (f1 - f0)


def _column(name: str, column: int, wavelengths: TensorLike, *, extend: str | None = None,
            scale: float = 1.0) -> torch.Tensor:
    """Interpolate column ``column`` of table ``name`` at ``wavelengths`` (nm).

    ``extend``: None raises outside the table; "zero" returns 0 outside; "hold" holds the end values.
    """
    wl = as_tensor(wavelengths)
    _, arr = table(name)
    lo, hi = float(arr[0, 0]), float(arr[-1, 0])
    if extend is None:
        check_range(f"wavelengths (table {name!r})", wl, lo, hi, "nm")
    xp = torch.as_tensor(arr[:, 0], dtype=wl.dtype, device=wl.device)
    fp = torch.as_tensor(arr[:, column] * scale, dtype=wl.dtype, device=wl.device)
    out = interp(wl, xp, fp)
    if extend == "zero":
        out = torch.where((wl < lo) | (wl > hi), torch.zeros_like(out), out)
    elif extend == "hold":
        out = torch.where(wl < lo, fp[0], torch.where(wl > hi, fp[-1], out))
    return out


# --------------------------------------------------------------------------------------------- chromophores
def water(wavelengths: TensorLike, source: str = "segelstein") -> torch.Tensor:
    """Absorption coefficient of pure water, cm^-1 (Segelstein 1981, or Hale & Querry 1973)."""
    name = {"segelstein": "water_segelstein", "hale_querry": "water_hale_querry"}.get(source)
    if name is None:
        raise ValueError(f"source must be 'segelstein' or 'hale_querry', got {source!r}")
    return _column(name, 1, wavelengths)


def melanosome(wavelengths: TensorLike) -> torch.Tensor:
    """Melanosome absorption, cm^-1: 6.6e11 * lambda^-3.33 (thesis eq 2.4.2, after Jacques 1996)."""
    wl = as_tensor(wavelengths)
    check_range("wavelengths (melanosome)", wl, 200.0, 3000.0, "nm")
    return 6.6e11 * wl.pow(-3.33)


def _hb_conc_molar() -> float:
    return HB_GRAMS_PER_LITRE / HB_MOLAR_MASS


def _hemoglobin_table() -> np.ndarray:
    """Hemoglobin-only mu_a of whole blood (cm^-1), columns wl, oxy, deoxy on a 1 nm grid 400-1995 nm, from the
    tables of the current ``tables_version()``."""
    return _hemoglobin_table_at(tables_version())


@functools.lru_cache(maxsize=1)
def _hemoglobin_table_at(version: int) -> np.ndarray:
    """``_hemoglobin_table`` at table version ``version`` (the cache key: a replaced table is never served)."""
    _, prahl = table("hemoglobin_prahl")
    _, boss = table("whole_blood_bosschaart")
    _, wat = table("water_segelstein")
    grid = np.arange(400.0, 1996.0, 1.0)  # 1 nm steps
    k = LN10 * _hb_conc_molar()
    p_oxy = np.interp(grid, prahl[:, 0], prahl[:, 1] * k)
    p_de = np.interp(grid, prahl[:, 0], prahl[:, 2] * k)
    b_oxy = np.interp(grid, boss[:, 0], boss[:, 1] * 10.0)  # mm^-1 -> cm^-1
    b_de = np.interp(grid, boss[:, 0], boss[:, 2] * 10.0)
    w = np.interp(grid, wat[:, 0], wat[:, 1])
    fw = blood_water_fraction_bosschaart()
    n_oxy = np.clip(b_oxy - fw * w, 0.0, None)
    n_de = np.clip(b_de - fw * w, 0.0, None)
    t = np.clip((grid - 900.0) / 100.0, 0.0, 1.0)  # cross-fade 900-1000 nm
    oxy = np.where(grid <= 1000, (1 - t) * p_oxy + t * n_oxy, n_oxy)
    de = np.where(grid <= 1000, (1 - t) * p_de + t * n_de, n_de)
    return np.stack([grid, oxy, de], axis=1)


def blood_water_fraction_bosschaart() -> float:
    """Water volume fraction of Bosschaart's whole blood: least squares over 1350-1650 nm, where water
    dominates its absorption (see README)."""
    _, boss = table("whole_blood_bosschaart")
    _, wat = table("water_segelstein")
    grid = np.arange(1350.0, 1651.0)
    b = 0.5 * (np.interp(grid, boss[:, 0], boss[:, 1]) + np.interp(grid, boss[:, 0], boss[:, 2])) * 10
    w = np.interp(grid, wat[:, 0], wat[:, 1])
    return float(np.sum(b * w) / np.sum(w * w))


def hemoglobin(wavelengths: TensorLike) -> tuple[torch.Tensor, torch.Tensor]:
    """Hemoglobin-only absorption of whole blood (150 g/L), cm^-1: ``(oxy, deoxy)``, 400-1995 nm.

    Prahl's extinction in the visible, Bosschaart's whole blood minus its water above 1000 nm (README).
    """
    wl = as_tensor(wavelengths)
    arr = _hemoglobin_table()
    check_range("wavelengths (hemoglobin)", wl, float(arr[0, 0]), float(arr[-1, 0]), "nm")
    xp = torch.as_tensor(arr[:, 0], dtype=wl.dtype, device=wl.device)
    fp = torch.as_tensor(arr[:, 1:].T.copy(), dtype=wl.dtype, device=wl.device)
    out = interp(wl, xp, fp)
    return out[0], out[1]


def bilirubin(wavelengths: TensorLike, concentration_molar: float = 8.5e-6) -> torch.Tensor:
    """Bilirubin absorption, cm^-1, at ``concentration_molar`` (default 8.5 uM, ~0.5 mg/dL, normal plasma).

    PhotochemCAD extinction (240-700 nm); zero beyond 700 nm, where bilirubin does not absorb. Negative
    noise values in the table are clipped to zero.
    """
    wl = as_tensor(wavelengths)
    check_range("wavelengths (bilirubin)", wl, 240.0, 3000.0, "nm")
    return _column("bilirubin_li", 1, wl, extend="zero", scale=LN10 * concentration_molar).clamp_min(0.0)


def beta_carotene(wavelengths: TensorLike, concentration_molar: float = 1.0e-6) -> torch.Tensor:
    """Beta-carotene absorption, cm^-1, at ``concentration_molar`` (approximate table, see README)."""
    return _column("beta_carotene_approx", 1, wavelengths, scale=LN10 * concentration_molar)


def collagen(wavelengths: TensorLike) -> torch.Tensor:
    """Absorption of pure collagen, cm^-1 (approximate table after Sekar et al. 2017, see README)."""
    return _column("collagen_approx", 1, wavelengths)


def salomatina(tissue: str, wavelengths: TensorLike) -> tuple[torch.Tensor, torch.Tensor]:
    """Ex-vivo ``(mu_a, mu_s')`` in cm^-1 of ``tissue`` in {'epidermis', 'dermis', 'hypodermis'}."""
    if tissue not in ("epidermis", "dermis", "hypodermis"):
        raise ValueError(f"tissue must be 'epidermis', 'dermis' or 'hypodermis', got {tissue!r}")
    name = f"skin_{tissue}_salomatina"
    return _column(name, 1, wavelengths, scale=10.0), _column(name, 3, wavelengths, scale=10.0)


def clear_caches() -> None:
    """Empty this module's caches (the packaged files read, the hemoglobin table derived from them). Never
    needed for correctness: derived values are keyed on ``tables_version()``; this only frees memory."""
    _read_csv.cache_clear()
    _hemoglobin_table_at.cache_clear()


__all__ = [
    "available_tables",
    "beta_carotene",
    "bilirubin",
    "clear_caches",
    "collagen",
    "hemoglobin",
    "interp",
    "melanosome",
    "register_table",
    "salomatina",
    "table",
    "tables_version",
    "unregister_table",
    "water",
]
