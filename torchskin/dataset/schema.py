"""The dataset schema, in one place: the schema version this torchskin writes and those it reads, every column of a
shard (``COLUMNS``: the fixed columns, one reflectance column per index band, the stored indices), and the
normalized differences of index-band pairs (``INDICES``: NDGRI, NDSI, NDVN) with ``Rows``, the rows a reader gets
(``dataset.files.read_rows``), which computes any band pair's normalized difference one way (``Rows.nd``).

The generator (``dataset.generate``) writes these columns; training, evaluation and the examples read them through
``read_rows``. Plain data and numpy: importing it loads no torch, no renderer, no detector (``dataset verify`` and every
reader import it; ``detectors.features`` re-exports ``BAND_COLUMNS`` from here); ``Rows.nd`` loads ``torchskin.detect``,
the formula's home, when first called.
"""

from __future__ import annotations

import functools
import operator
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..bands import INDEX_BANDS, INDEX_BANDS_NM, Band, BandSet

if TYPE_CHECKING:
    from numpy.typing import DTypeLike

#: the dataset schema this torchskin writes. What each version changed: 2: elm_valid column, level panels (tilted
#: towards low cameras: ``generate.panel_tilt_deg``); 3: surface, clothing and material columns, clothing drawn from
#: earthlib; 4: the light model's atmosphere and each pixel's light (sky_view, direct_share_*, light, backlit),
#: sky_fraction derived; 5: one set of pixels per pose group (every sun x skin of a group shades the same 2 x
#: pixels_per_class pixels), panel medians from a capped sample (``generate.PANEL_SAMPLE``); 6:
#: panel_irradiance_ratio column, elm_valid false where it exceeds ``render.elm.ELM_MAX_IRRADIANCE_RATIO``, and
#: elm_line_valid (elm_valid without that bound). Band sets (``generate --bands``, ``[bands]``) kept 6: the index
#: bands' rows are the same bytes; another set's reflectance columns are its ``BandSet.columns`` (``columns_for``),
#: named in the manifest's ``bands`` (``files.dataset_bands``: the index bands where a manifest has none)
SCHEMA_VERSION = 6
#: the schemas this torchskin reads: every one it ever wrote (a reader checks the columns it needs,
#: ``files.open_dataset``); a manifest of any other version, such as a newer torchskin's, is refused
#: (``files.manifest``)
READ_SCHEMAS = range(1, SCHEMA_VERSION + 1)


def band_column(band: Band | float) -> str:
    """The dataset column of the ELM reflectance in a band (``BandSet.columns``: ``r`` and its ``Band.label``).

    >>> band_column(1080.0), band_column(Band(544.5))
    ('r1080', 'r544.5')
    """
    return BandSet.of([band]).columns[0]


#: the dataset columns of the ELM reflectance in the four index bands (``INDEX_BANDS_NM``: g, r, n, s), in order
BAND_COLUMNS: tuple[str, ...] = INDEX_BANDS.columns

#: one side of a normalized difference: the index bands (nm) whose reflectances it sums
Side = tuple[float, ...]
_G, _R, _N, _S = INDEX_BANDS_NM
#: the normalized differences (a - b) / (a + b) of index-band sums (``detect.ratio_indices``, whose tensor form the
#: detectors use): NDGRI (green - red), NDSI (NIR - SWIR, eq 2.5.8) and NDVN (visible - NIR: g + r against n + s)
INDICES: dict[str, tuple[Side, Side]] = {"ndgri": ((_G,), (_R,)), "ndsi": ((_N,), (_S,)),
                                         "ndvn": ((_G, _R), (_N, _S))}
#: the indices a shard stores (the renderer's, from its float32 ELM reflectance); readers compute NDVN (``Rows.nd``)
STORED_INDICES = ("ndgri", "ndsi")


def index_formula(name: str) -> str:
    """An index of ``INDICES`` written over the band columns.

    >>> index_formula("ndgri"), index_formula("ndvn")
    ('(r544 - r633) / (r544 + r633)', '((r544 + r633) - (r1080 + r1580)) / ((r544 + r633) + (r1080 + r1580))')
    """
    def side(nm: Side) -> str:
        cols = " + ".join(band_column(w) for w in nm)
        return cols if len(nm) == 1 else f"({cols})"

    a, b = (side(s) for s in INDICES[name])
    return f"({a} - {b}) / ({a} + {b})"


#: the columns whose meaning does not depend on the bands: name -> (pyarrow type name, description, unit)
FIXED_COLUMNS: dict[str, tuple[str, str, str]] = {
    "group": ("int32", "pose group index", ""),
    "sun": ("int16", "sun index within the group", ""),
    "skin": ("int16", "skin index within the group", ""),
    "label": ("bool", "true: skin pixel (from the G-buffer)", ""),
    "sun_zenith_deg": ("float32", "sun zenith", "deg"),
    "sun_azimuth_deg": ("float32", "sun azimuth (from +x towards +y)", "deg"),
    "camera_zenith_deg": ("float32", "camera zenith", "deg"),
    "camera_azimuth_deg": ("float32", "camera azimuth", "deg"),
    "relative_azimuth_deg": ("float32", "|sun azimuth - camera azimuth| folded to [0, 180]", "deg"),
    "range_m": ("float32", "camera range to the subject", "m"),
    "backlit": ("bool", "the camera looks towards the sun: relative azimuth >= 120 deg (BACKLIT_MIN_DEG)", ""),
    "aerosol_500nm": ("float32", "light model atmosphere: aerosol optical depth at 500 nm (NaN: a light model "
                      "without an atmosphere, thesis)", ""),
    "precipitable_water_cm": ("float32", "light model atmosphere: precipitable water (NaN: thesis)", "cm"),
    "ozone_atm_cm": ("float32", "light model atmosphere: total ozone (NaN: thesis)", "atm-cm"),
    "pressure_pa": ("float32", "light model atmosphere: surface pressure (NaN: thesis)", "Pa"),
    "day_of_year": ("int16", "light model atmosphere: day of year, 1-366 (0: thesis, a light model without an "
                    "atmosphere)", ""),
    "sky_fraction": ("float32", "derived: diffuse horizontal / direct normal irradiance at 544 nm", ""),
    "atmosphere_transmittance": ("float32", "sensor path transmittance at 544 nm", ""),
    "path_radiance_scale": ("float32", "path radiance scale (spectrl2: of Koschmieder's airlight; thesis: of the "
                            "sensor default)", ""),
    "skin_type": ("string", "Fitzpatrick type of the group's skin", ""),
    "melanosome": ("float32", "melanosome volume fraction", ""),
    "blood": ("float32", "blood level", ""),
    "oxygenation": ("float32", "blood oxygen saturation", ""),
    "reticular_depth": ("float32", "reticular dermis thickness", "cm"),
    "collagen": ("float32", "reticular collagen fraction", ""),
    "subcutaneous_scale": ("float32", "subcutaneous reflectance scale", ""),
    "subject_yaw_deg": ("float32", "subject yaw", "deg"),
    "head_yaw_deg": ("float32", "anny head turn (NaN for mesh files)", "deg"),
    "head_pitch_deg": ("float32", "anny head tilt (NaN for mesh files)", "deg"),
    "gender": ("float32", "anny phenotype in [0, 1] (NaN for mesh files)", ""),
    "age": ("float32", "anny phenotype", ""),
    "muscle": ("float32", "anny phenotype", ""),
    "weight": ("float32", "anny phenotype", ""),
    "height": ("float32", "anny phenotype", ""),
    "proportions": ("float32", "anny phenotype", ""),
    "subject": ("string", "subject source (anny or the mesh path)", ""),
    "surface": ("string", "skin surface model of eq 3.1.1 (thesis or conserving)", ""),
    "clothing": ("string", "earthlib spectrum name of the subject's clothing (empty: the fixed clothing spectrum)", ""),
    "panels": ("string", "reference panel kind", ""),
    "material": ("string", "what the pixel shows: skin, clothing, ground or confuser", ""),
    "confuser": ("string", "earthlib confuser spectrum name (empty: none)", ""),
    "theta_i_deg": ("float32", "local incidence angle", "deg"),
    "theta_r_deg": ("float32", "local view angle", "deg"),
    "delta_phi_deg": ("float32", "local relative azimuth (180: forward plane)", "deg"),
    "shadow": ("bool", "not sunlit: the sun is occluded (cast shadow) or behind the surface (θi > 90°)", ""),
    "light": ("string", "sunlit or shadow (no direct sun: not shadow, resp. shadow)", ""),
    "sky_view": ("float32", "the pixel's cosine-weighted view of the sky (hemisphere rays; NaN: a light without sky or "
                 "ground light, none cast)", ""),
    "direct_share_544": ("float32", "share of the pixel's irradiance at 544 nm that is direct (sun and circumsolar)",
                         ""),
    "direct_share_1580": ("float32", "share of the pixel's irradiance at 1580 nm that is direct", ""),
    "panel_irradiance_ratio": ("float32", "the most irradiance a surface facing the sun and sky receives over the "
                               "reference panels' (render.elm.panel_irradiance_ratio): sunlit surfaces read up to this "
                               "many times their reflectance through the empirical line", ""),
    "elm_valid": ("bool", "the frame's ELM is physical: both reference panels sunlit (>= half of each interior), "
                  "their signals >= 20 sigma of the medians' noise apart in every band, a positive finite gain "
                  "(render.elm.elm_line_valid), and panel_irradiance_ratio <= 3 (ELM_MAX_IRRADIANCE_RATIO); "
                  "evaluation and calibration use only these frames", ""),
    "elm_line_valid": ("bool", "elm_valid but for the irradiance-ratio bound: panels sunlit and the line a line; "
                       "torchskin train --frames line (its default) also learns from these frames", ""),
}

#: the columns defined at one index band only (nm): NaN in the rows of a band set without a band within
#: ``bands.BAND_MATCH_NM`` of it (``columns_for``)
SINGLE_BAND_COLUMNS: dict[str, float] = {"sky_fraction": _G, "atmosphere_transmittance": _G, "direct_share_544": _G,
                                         "direct_share_1580": _S}


def has_band(bands: BandSet, nm: float) -> bool:
    """Whether ``bands`` holds a band at ``nm`` (within ``bands.BAND_MATCH_NM``; ``BandSet.index``).

    >>> has_band(INDEX_BANDS, 1580.0), has_band(BandSet.of([544.0, 633.0]), 1580.0)
    (True, False)
    """
    try:
        bands.index(nm)
    except ValueError:
        return False
    return True


def columns_for(bands: BandSet) -> dict[str, tuple[str, str, str]]:
    """Every Parquet column of a shard of a dataset rendered in ``bands``, in order: name -> (pyarrow type name,
    description, unit). The fixed columns, then the ELM reflectance in each band (``BandSet.columns``), then the
    stored indices (``STORED_INDICES``). A column defined at bands the set lacks (an index, or one of
    ``SINGLE_BAND_COLUMNS``) is NaN, and its description says so; with the index bands, ``COLUMNS``.

    >>> c = columns_for(BandSet.parse("450,544,633"))
    >>> [k for k in c if k.startswith("r") and k[1:].isdigit()], c["ndsi"][1]
    (['r450', 'r544', 'r633'], '(r1080 - r1580) / (r1080 + r1580) (NaN: the bands lack 1080, 1580 nm)')
    """
    def lacking(nm: Sequence[float]) -> str:
        gone = [f"{w:g}" for w in nm if not has_band(bands, w)]
        return f" (NaN: the bands lack {', '.join(gone)} nm)" if gone else ""

    fixed = {k: (t, d + lacking([SINGLE_BAND_COLUMNS[k]]) if k in SINGLE_BAND_COLUMNS else d, u)
             for k, (t, d, u) in FIXED_COLUMNS.items()}
    return {**fixed,
            **{col: ("float32", f"ELM reflectance at {b.label} nm", "") for b, col in zip(bands, bands.columns)},
            **{name: ("float32", index_formula(name) + lacking([*INDICES[name][0], *INDICES[name][1]]), "")
               for name in STORED_INDICES}}


#: every Parquet column of a shard of the index bands (``columns_for(INDEX_BANDS)``), in order: name -> (pyarrow
#: type name, description, unit). The fixed columns, then the ELM reflectance in each index band
#: (``BAND_COLUMNS``), then the stored indices (``STORED_INDICES``)
COLUMNS: dict[str, tuple[str, str, str]] = columns_for(INDEX_BANDS)


def _bands_of(side: float | Sequence[float]) -> Side:
    return (float(side),) if isinstance(side, (int, float, np.number)) else tuple(float(w) for w in side)


@dataclass(frozen=True)
class Rows:
    """Rows of a dataset (``dataset.files.read_rows``): each column read as a numpy array, all of one length.

    Attributes:
        columns: column name -> values (strings as object arrays), in the order they were asked for.
        excluded: rows of the dataset left out because their frame's ELM was not in the frame set read.
        band_set: the dataset's bands (its manifest's ``bands``; the index bands for datasets written before
            manifests recorded them): ``nd`` finds a wavelength's column here.
    """

    columns: dict[str, np.ndarray]
    excluded: int = 0
    band_set: BandSet = INDEX_BANDS

    def __len__(self) -> int:
        return len(next(iter(self.columns.values()))) if self.columns else 0

    def __getitem__(self, name: str) -> np.ndarray:
        return self.columns[name]

    def stack(self, names: Sequence[str], dtype: DTypeLike | None = None) -> np.ndarray:
        """The columns ``names`` side by side, (n, len(names)), converted to ``dtype`` (None: numpy's common type)."""
        out = np.stack([self.columns[c] for c in names], -1)
        return out if dtype is None else out.astype(dtype)

    def bands(self, dtype: DTypeLike = np.float32) -> np.ndarray:
        """The ELM reflectance in the index bands, (n, 4) in ``INDEX_BANDS_NM`` order (``BAND_COLUMNS``)."""
        return self.stack(BAND_COLUMNS, dtype)

    def nd(self, a_nm: float | Sequence[float], b_nm: float | Sequence[float],
           dtype: DTypeLike = np.float64) -> np.ndarray:
        """The normalized difference (a - b) / (a + b) of two index bands, or of two sums of them, per row.

        Args:
            a_nm, b_nm: a band centre (nm; its column is the ``band_set``'s band within ``bands.BAND_MATCH_NM``)
                or several, whose reflectances are summed in the order given (NDVN: ``(544, 633)`` against ``(1080, 1580)``; ``INDICES`` names the indices).
            dtype: the float type every step is computed in (the columns are float32; float64 by default).

        Returns:
            (n,) of ``dtype``; NaN where a + b is 0 (no warning). The formula is ``detect.normalized_difference``'s,
            the one the detectors' ``detect.ratio_indices`` uses: the same bits for the same dtype.

        >>> r = Rows({"r544": np.array([0.3, 0.0], np.float32), "r633": np.array([0.6, 0.0], np.float32)})
        >>> r.nd(544, 633).round(4).tolist()
        [-0.3333, nan]
        """
        from ..detect import normalized_difference

        def side(nm: Side) -> np.ndarray:
            cols = [self.band_set.columns[self.band_set.index(w)] for w in nm]
            return functools.reduce(operator.add, [self.columns[c].astype(dtype) for c in cols])

        a, b = side(_bands_of(a_nm)), side(_bands_of(b_nm))
        with np.errstate(divide="ignore", invalid="ignore"):
            return normalized_difference(a, b)

    def index(self, name: str, dtype: DTypeLike = np.float64) -> np.ndarray:
        """An index of ``INDICES`` ("ndgri", "ndsi", "ndvn") computed from the band columns (``nd``). The stored
        ``ndgri`` and ``ndsi`` columns are the renderer's own, read as columns."""
        a, b = INDICES[name]
        return self.nd(a, b, dtype)


__all__ = ["BAND_COLUMNS", "COLUMNS", "FIXED_COLUMNS", "INDICES", "READ_SCHEMAS", "SCHEMA_VERSION",
           "SINGLE_BAND_COLUMNS", "STORED_INDICES", "Rows", "Side", "band_column", "columns_for", "has_band",
           "index_formula"]
