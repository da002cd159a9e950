"""Spectral bands: ``Band(center_nm, fwhm_nm)`` with Gaussian response; fwhm 0 means monochromatic; or a measured
response curve (``Band.from_response``, a camera's response table: ``BandSet.from_csv``).

A camera's bands as data: ``BandSet``, read from the ``--bands`` text (``BandSet.parse``, the one parser of band
lists), named as dataset columns (``BandSet.columns``) and written as JSON (``BandSet.to_json``).

Band values of a spectrum are response-weighted means over wavelength (a flat source spectrum; weight by
the source yourself when it matters). Shapes: spectra are ``(..., n_grid)``, band values ``(..., n_bands)``.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, cast

if TYPE_CHECKING:  # torch loads with the functions that compute: the band definitions are plain data
    import numpy as np
    import torch

    from ._checks import TensorLike

FWHM_TO_SIGMA = 1.0 / (2.0 * math.sqrt(2.0 * math.log(2.0)))
SUPPORT_FWHM = 1.5  # a band's response is truncated at centre +- 1.5 FWHM (+- 3.5 sigma)
#: most wavelengths a sampling grid (``band_sampling``, ``tissue.wavelength_grid``) may have: refused before
#: anything is allocated (1e6 points is about 1 pm steps over the model's 400-1700 nm); ``band_sampling``'s
#: weight matrix (grid x bands) may hold at most 16 times as many entries
MAX_GRID_POINTS = 1_000_000


#: the wavelengths the skin model covers, nm (its absorption tables' common range; ``tissue.MODEL_RANGE_NM``)
MODEL_RANGE_NM = (400.0, 1700.0)


@dataclass(frozen=True)
class Band:
    """A spectral band: centre and full width at half maximum of a Gaussian response, both in nm; or a measured
    response curve (``response``: wavelengths in nm, increasing, and the relative response there, peak 1), whose
    centroid and FWHM are ``center_nm`` and ``fwhm_nm`` (``Band.from_response``).

    >>> b = Band.from_response([540, 550, 560, 570, 580], [0, 0.5, 1, 0.5, 0])
    >>> b.center_nm, b.fwhm_nm, b.support
    (560.0, 20.0, (540.0, 580.0))
    """

    center_nm: float
    fwhm_nm: float = 0.0
    response: tuple[tuple[float, ...], tuple[float, ...]] | None = None

    def __post_init__(self) -> None:
        if not (self.center_nm > 0 and math.isfinite(self.center_nm)):
            raise ValueError(f"center_nm must be a positive finite wavelength in nm, got {self.center_nm}")
        if not (self.fwhm_nm >= 0 and math.isfinite(self.fwhm_nm)):
            raise ValueError(f"fwhm_nm must be >= 0 nm, got {self.fwhm_nm}")
        if self.response is not None:
            wl, r = _checked_response(*self.response)
            object.__setattr__(self, "response", (tuple(wl), tuple(r)))
            if not self.fwhm_nm > 0:
                raise ValueError("a band with a response curve needs its FWHM (> 0 nm): use Band.from_response")

    @classmethod
    def from_response(cls, wavelengths_nm: Sequence[float], values: Sequence[float]) -> Band:
        """The band of a measured response curve: ``values`` at the increasing ``wavelengths_nm`` (any scale,
        >= 0, linear between samples, 0 outside), kept scaled to a peak of 1. Its centre is the curve's centroid
        (to 0.01 nm) and its FWHM the width between the outermost half-maximum crossings. ``ValueError`` for a
        curve that is not finite, negative, all zero or not on increasing wavelengths."""
        import numpy as np

        wl, r = (np.asarray(x, dtype=np.float64) for x in _checked_response(wavelengths_nm, values))
        area = float(np.sum(0.5 * (r[1:] + r[:-1]) * np.diff(wl)))
        if not area > 0:
            raise ValueError("response: a single non-zero sample at the table's end encloses no area")
        x0, x1, r0, r1 = wl[:-1], wl[1:], r[:-1], r[1:]  # the curve linear between samples: exact moments
        centre = float(np.sum((x1 - x0) / 6 * (r0 * (2 * x0 + x1) + r1 * (x0 + 2 * x1)))) / area
        above = np.nonzero(r >= 0.5)[0]
        i, j = int(above[0]), int(above[-1])
        left = wl[i] if i == 0 else wl[i - 1] + (0.5 - r[i - 1]) / (r[i] - r[i - 1]) * (wl[i] - wl[i - 1])
        right = wl[j] if j == len(wl) - 1 else wl[j] + (r[j] - 0.5) / (r[j] - r[j + 1]) * (wl[j + 1] - wl[j])
        return cls(round(centre, 2), round(float(right - left), 2) if right > left else float(np.min(np.diff(wl))),
                   (tuple(wl.tolist()), tuple(r.tolist())))

    @property
    def support(self) -> tuple[float, float]:
        """The wavelengths (nm) where the response is not zero: centre +- ``SUPPORT_FWHM`` FWHM for a Gaussian
        band, a response curve's non-zero samples and their outer neighbours."""
        if self.response is not None:
            wl, r = self.response
            nz = [k for k, v in enumerate(r) if v > 0]
            return wl[max(nz[0] - 1, 0)], wl[min(nz[-1] + 1, len(wl) - 1)]
        h = SUPPORT_FWHM * self.fwhm_nm
        return self.center_nm - h, self.center_nm + h

    @property
    def label(self) -> str:
        """The centre as written in file names, titles and dataset columns (``band_<label>nm.png``, ``r<label>``):
        six significant digits, trailing zeros dropped (``f"{center_nm:g}"``): 544.0 is ``544``, 544.5 ``544.5``."""
        return f"{self.center_nm:g}"

    def describe(self) -> str:
        """The band in words for messages: ``1080/20`` (centre/FWHM nm), with ``(response curve)`` for a curve."""
        return f"{self.center_nm:g}/{self.fwhm_nm:g}" + (" (response curve)" if self.response is not None else "")

    def to_dict(self) -> dict:
        """``{"center_nm", "fwhm_nm"}``, and ``"response": {"wavelengths_nm", "values"}`` for a curve: an item of
        ``BandSet.to_json`` and of a scene's ``bands``."""
        d: dict = {"center_nm": self.center_nm, "fwhm_nm": self.fwhm_nm}
        if self.response is not None:
            d["response"] = {"wavelengths_nm": list(self.response[0]), "values": list(self.response[1])}
        return d


def _checked_response(wavelengths_nm: Sequence[float], values: Sequence[float]) -> tuple[list[float], list[float]]:
    """A response curve's wavelengths and values as floats, the values scaled to a peak of 1; ``ValueError`` in
    one line unless the wavelengths are finite, positive and strictly increasing (at least two) and the values
    finite, >= 0 and not all zero."""
    try:
        wl = [float(x) for x in wavelengths_nm]
        r = [float(x) for x in values]
    except (TypeError, ValueError):
        raise ValueError("response: wavelengths and values must be numbers") from None
    if len(wl) != len(r) or len(wl) < 2:
        raise ValueError(f"response: needs at least two wavelengths, each with a value; got {len(wl)} wavelengths "
                         f"and {len(r)} values")
    bad = next((x for x in wl if not (math.isfinite(x) and x > 0)), None)
    if bad is not None:
        raise ValueError(f"response: wavelengths must be positive finite nm, got {bad}")
    k = next((k for k in range(1, len(wl)) if wl[k] <= wl[k - 1]), None)
    if k is not None:
        raise ValueError(f"response: wavelengths must strictly increase, got {wl[k - 1]:g} then {wl[k]:g} nm")
    k = next((k for k, v in enumerate(r) if not (math.isfinite(v) and v >= 0)), None)
    if k is not None:
        raise ValueError(f"response: values must be finite and >= 0, got {r[k]} at {wl[k]:g} nm")
    peak = max(r)
    if not peak > 0:
        raise ValueError("response: every value is zero")
    return wl, [v / peak for v in r]


#: Centres (nm) of the thesis's four detection bands, green, red, NIR and SWIR, in this order: the bands of the
#: NDGRI (544, 633 nm) and NDSI (1080, 1580 nm) rules. The one place these numbers are written.
INDEX_BANDS_NM: tuple[float, ...] = (544.0, 633.0, 1080.0, 1580.0)


#: a per-band setting (``per_band``): one number, one value per band, four values at the ``INDEX_BANDS_NM``, or a
#: spectrum given at wavelengths (``at_wavelengths``)
PerBand = float | Sequence[float] | Mapping[str, Sequence[float]]


def as_bands(bands: Iterable[Band | float | Sequence[float] | Mapping] | None) -> tuple[Band, ...]:
    """Normalise a band specification (Band objects, centres, (centre, fwhm) pairs, or ``Band.to_dict`` items)."""
    if bands is None:
        return DEFAULT_BANDS
    out = []
    for b in bands:
        if isinstance(b, Band):
            out.append(b)
            continue
        if isinstance(b, Mapping):
            out.append(band_from_dict(b, f"band {str(b)[:80]}"))
            continue
        try:
            if isinstance(b, (tuple, list)):
                if len(b) not in (1, 2):
                    raise ValueError
                out.append(Band(float(b[0]), float(b[1]) if len(b) == 2 else 0.0))
            else:
                out.append(Band(float(cast(float, b))))
        except (TypeError, ValueError) as e:
            msg = f": {e}" if str(e) else ""
            raise ValueError(f"band {b!r} must be a centre or (centre, fwhm) in nm{msg}") from None
    if not out:
        raise ValueError("bands must name at least one band")
    return tuple(out)


def band_from_dict(d: Mapping, what: str) -> Band:
    """The band of a ``Band.to_dict`` item; ``ValueError`` starting with ``what`` for anything else."""
    c, f, resp = d.get("center_nm"), d.get("fwhm_nm", 0.0), d.get("response")
    if not (set(d) <= {"center_nm", "fwhm_nm", "response"}
            and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in (c, f))):
        raise ValueError(f"{what} must be {{\"center_nm\": nm, \"fwhm_nm\": nm}} (numbers), with an optional "
                         f"\"response\": {{\"wavelengths_nm\": [...], \"values\": [...]}}; got {str(dict(d))[:100]}")
    try:
        if resp is None:
            return Band(float(c), float(f))  # type: ignore[arg-type]  # numbers, checked above
        if not (isinstance(resp, Mapping) and set(resp) == {"wavelengths_nm", "values"}):
            raise ValueError("response must be {\"wavelengths_nm\": [...], \"values\": [...]}")
        return Band(float(c), float(f), (resp["wavelengths_nm"], resp["values"]))  # type: ignore[arg-type]
    except (TypeError, ValueError) as e:
        raise ValueError(f"{what}: {e}") from None


def scene_bands(bands: Iterable[Band]) -> list:
    """Bands as a scene holds them (``render.scene.Scene.bands``, plain JSON data): ``[centre, fwhm]`` pairs, and
    ``Band.to_dict`` for a measured response curve."""
    return [[b.center_nm, b.fwhm_nm] if b.response is None else b.to_dict() for b in bands]


def check_band_within(band: Band, lo: float, hi: float) -> None:
    """``ValueError`` unless the band's response (centre +- ``SUPPORT_FWHM`` FWHM, or its curve's non-zero part)
    lies within ``lo..hi`` nm."""
    s_lo, s_hi = band.support
    if s_lo >= lo - 1e-9 and s_hi <= hi + 1e-9:
        return
    c, f = band.center_nm, band.fwhm_nm
    if band.response is not None:
        hint = " (wavelengths in µm? a response table's are nm)" if s_hi < 10 else ""
        raise ValueError(f"band {band.describe()} nm: its response spans {s_lo:g}..{s_hi:g} nm, outside the "
                         f"model's {lo:g}-{hi:g} nm{hint}")
    if not (lo <= c <= hi):
        raise ValueError(f"band {c:g}/{f:g} nm: the centre lies outside the model's {lo:g}-{hi:g} nm")
    fmax = min(c - lo, hi - c) / SUPPORT_FWHM
    raise ValueError(f"band {c:g}/{f:g} nm: its response (centre +- {SUPPORT_FWHM:g} FWHM) spans {s_lo:g}..{s_hi:g}"
                     f" nm, outside the model's {lo:g}-{hi:g} nm; the FWHM may be at most {fmax:.4g} nm at this centre")


#: named band sets for ``--bands NAME``: the list each stands for, and its source
BAND_PRESETS: dict[str, tuple[str, str]] = {
    "thesis": ("544,633,1080,1580", "the thesis's four detection bands (INDEX_BANDS_NM), monochromatic"),
    "rededge-mx": ("475/32,560/27,668/14,717/12,842/57",
                   "MicaSense RedEdge-MX, centre/FWHM nm: blue, green, red, red edge, NIR, as MicaSense's knowledge "
                   "base lists them ('What is the center wavelength and bandwidth of each filter for MicaSense "
                   "sensors?', support.micasense.com; the RedEdge 3 and RedEdge-M user guides give narrower "
                   "widths, 475/20, 560/20, 668/10, 717/10, 840/40)"),
}

#: most bands one ``START:STOP:STEP`` range of ``--bands`` may expand to
MAX_RANGE_BANDS = 10_000


def range_numbers(text: str, option: str) -> tuple[float, float, float]:
    """START, STOP and STEP of a range ``START:STOP:STEP`` (a ``--bands`` range, ``spectra --wavelengths``).

    The caller checks what they mean. ``ValueError`` naming ``option`` unless ``text`` is three numbers.

    >>> range_numbers("450:1650:10", "--wavelengths")
    (450.0, 1650.0, 10.0)
    >>> range_numbers("400-800", "--wavelengths")
    Traceback (most recent call last):
    ...
    ValueError: --wavelengths must be START:STOP:STEP in nm, got '400-800'
    """
    parts = text.split(":")
    if len(parts) != 3:
        raise ValueError(f"{option} must be START:STOP:STEP in nm, got {text!r}")
    try:
        start, stop, step = (float(p) for p in parts)
    except ValueError:
        raise ValueError(f"{option} must be numbers START:STOP:STEP, got {text!r}") from None
    return start, stop, step


def expand_band_items(text: str, option: str = "--bands") -> list[str]:
    """The items ``centre[/fwhm]`` of a band list (comma-separated), each range ``START:STOP:STEP[/FWHM]``
    expanded to START, START + STEP, ... up to STOP inclusive (STOP is in it when it lies on the step, within
    1e-6 of a step), each with the range's FWHM, and each preset name (``BAND_PRESETS``) to its bands.
    ``ValueError`` naming ``option`` for an empty item or a bad range (STEP > 0, STOP >= START, at most
    ``MAX_RANGE_BANDS`` bands).

    >>> expand_band_items("450:480:10/5,1580")
    ['450/5', '460/5', '470/5', '480/5', '1580']
    >>> expand_band_items("rededge-mx")
    ['475/32', '560/27', '668/14', '717/12', '842/57']
    >>> len(expand_band_items("450:1650:10"))
    121
    """
    out: list[str] = []
    for item in str(text).split(","):
        item = item.strip()
        if not item:
            raise ValueError(f"{option} has an empty item in {text!r} (use centre[/fwhm],... in nm)")
        if item.lower() in BAND_PRESETS:
            out += BAND_PRESETS[item.lower()][0].split(",")
            continue
        if ":" not in item:
            out.append(item)
            continue
        rng, _, f = item.partition("/")
        try:
            start, stop, step = range_numbers(rng, option)
        except ValueError:
            start = stop = step = math.nan
        if not (all(math.isfinite(v) for v in (start, stop, step)) and step > 0 and stop >= start):
            raise ValueError(f"bad band range {item!r} in {option} (use START:STOP:STEP[/FWHM] in nm, "
                             "STEP > 0, STOP >= START)")
        n = math.floor((stop - start) / step + 1e-6) + 1
        if n > MAX_RANGE_BANDS:
            raise ValueError(f"band range {item!r} in {option} gives {n} bands, more than {MAX_RANGE_BANDS}")
        suffix = f"/{f.strip()}" if f.strip() else ""
        out += [f"{round(start + k * step, 9):.12g}{suffix}" for k in range(n)]
    return out


#: how far (nm) a wavelength may lie from a band's centre and still be that band (``BandSet.index``,
#: ``onboard.match_bands``): a camera's nominal centres are rounded; the index bands are hundreds of nm apart
BAND_MATCH_NM = 2.0


@dataclass(frozen=True)
class BandSet:
    """A camera's bands as data: its bands (``Band``) in the cube's order, at least one.

    Read a ``--bands`` list, name its dataset columns, and keep it as JSON in a manifest:

    >>> b = BandSet.parse("544.5,633/20,1080:1100:10")
    >>> b.columns
    ('r544.5', 'r633', 'r1080', 'r1090', 'r1100')
    >>> b.index(1091.0)
    3
    >>> BandSet.from_json(b.to_json()) == b
    True
    >>> BandSet.parse("544/20").to_json()
    '[{"center_nm": 544.0, "fwhm_nm": 20.0}]'

    A band's column is ``r`` and its ``Band.label``: its centre to six significant digits, trailing zeros
    dropped. The index bands are the dataset's ``r544, r633, r1080, r1580``; 544.5 nm is ``r544.5``.
    """

    bands: tuple[Band, ...]

    def __post_init__(self) -> None:
        object.__setattr__(self, "bands", as_bands(tuple(self.bands)))

    @classmethod
    def of(cls, bands: Iterable[Band | float | tuple[float, float]]) -> BandSet:
        """The bands of ``Band`` objects, centres or ``(centre, fwhm)`` pairs (``as_bands``)."""
        return cls(as_bands(bands))

    @classmethod
    def parse(cls, text: str, within: tuple[float, float] | None = None, ordered: bool = True,
              option: str = "--bands") -> BandSet:
        """The bands of a ``--bands`` list: the one parser of band lists.

        Args:
            text: comma-separated bands ``centre[/fwhm]`` in nm, e.g. ``"544,633,1080/20,1580/40"`` (no fwhm:
                monochromatic), ranges ``START:STOP:STEP[/FWHM]`` (``expand_band_items``: ``450:1650:10`` is
                the 121 bands 450, 460, ..., 1650 nm) and preset names (``BAND_PRESETS``: ``rededge-mx``); or
                the path of a response table (``*.csv``: ``from_csv``); or a ``to_json`` list.
            within: ``(lo, hi)`` nm that every band's response (centre ± ``SUPPORT_FWHM`` FWHM) must lie in;
                default the skin model's 400-1700 nm (``tissue.MODEL_RANGE_NM``).
            ordered: the centres must strictly ascend, with distinct labels (``check_ascending``); a cube's
                bands as recorded (``io.parse_band_list``) may come in any order.
            option: the option named in errors.

        Returns:
            The bands; a one-line ``ValueError`` naming ``option`` and the bad item otherwise.

        >>> len(BandSet.parse("450:1650:10"))
        121
        >>> BandSet.parse("544,abc")
        Traceback (most recent call last):
        ...
        ValueError: bad band 'abc' in --bands (use centre[/fwhm] in nm): could not convert string to float: 'abc'
        """
        lo, hi = MODEL_RANGE_NM if within is None else within
        text = str(text).strip()
        if text.startswith("[") or text.lower().endswith(".csv"):  # a BandSet's JSON, a response table
            try:
                got = cls.from_json(text) if text.startswith("[") else cls.from_csv(text)
                for band in got:
                    check_band_within(band, lo, hi)
            except ValueError as e:
                raise ValueError(f"{option}: {e}") from None
            out = list(got.bands)
        else:
            out = []
            for item in expand_band_items(text, option):
                c, _, f = item.partition("/")
                try:
                    band = Band(float(c), float(f) if f else 0.0)
                    check_band_within(band, lo, hi)
                except ValueError as e:
                    raise ValueError(f"bad band {item!r} in {option} (use centre[/fwhm] in nm): {e}") from None
                out.append(band)
        if ordered:
            check_ascending(out, option)
        return cls(tuple(out))

    @classmethod
    def from_csv(cls, path: str | os.PathLike) -> BandSet:
        """The bands of a response table: a CSV file whose header names a wavelength column (nm) and then one
        column per band, each row a wavelength (increasing) and each band's response there (any scale, >= 0).
        Each column becomes ``Band.from_response``, in the file's order. ``ValueError`` naming the file and the
        problem (a missing file, a non-number, a NaN or negative response, wavelengths that do not increase).

        A measured camera's filter curves, for example::

            wavelength_nm,blue,green
            440,0.00,0.00
            460,0.52,0.00
            ...
        """
        import csv

        name = os.fspath(path)
        try:
            with open(name, newline="", encoding="utf-8") as fh:
                rows = [r for r in csv.reader(fh) if r and any(x.strip() for x in r)]
        except OSError as e:
            raise ValueError(f"response table {name}: cannot read it ({e.strerror or e})") from None
        except UnicodeDecodeError:
            raise ValueError(f"response table {name}: not a UTF-8 text CSV") from None
        if len(rows) < 3 or len(rows[0]) < 2:
            raise ValueError(f"response table {name}: needs a comma-separated header (wavelength_nm, then one column "
                             "per band) and at least two rows of numbers")
        width = len(rows[0])
        data = []
        for k, row in enumerate(rows[1:], start=2):
            if len(row) != width:
                raise ValueError(f"response table {name}: line {k} has {len(row)} values, the header {width}")
            try:
                data.append([float(x) for x in row])
            except ValueError:
                raise ValueError(f"response table {name}: line {k} holds a non-number: {','.join(row)[:80]}") from None
        wl = [r[0] for r in data]
        out = []
        for j, head in enumerate(rows[0][1:], start=1):
            try:
                out.append(Band.from_response(wl, [r[j] for r in data]))
            except ValueError as e:
                raise ValueError(f"response table {name}: column {head.strip()!r}: {e}") from None
        return cls(tuple(out))

    @classmethod
    def from_json(cls, data: str | Sequence[Mapping[str, object]]) -> BandSet:
        """The bands of ``to_json``'s text, or of its list already decoded (a manifest's entry).

        ``ValueError`` naming the problem for anything else.
        """
        try:
            items = json.loads(data) if isinstance(data, str) else data
        except ValueError as e:
            raise ValueError(f"band set JSON does not parse: {e}") from None
        if not isinstance(items, (list, tuple)) or not items:
            raise ValueError("band set JSON must be a non-empty list of bands {\"center_nm\": nm, \"fwhm_nm\": nm}, "
                             f"got {'an empty list' if isinstance(items, (list, tuple)) else type(items).__name__}")
        out = []
        for k, d in enumerate(items):
            if not isinstance(d, Mapping):
                raise ValueError(f"band set JSON: band {k} must be {{\"center_nm\": nm, \"fwhm_nm\": nm}} (numbers), "
                                 f"got {str(d)[:100]}")
            out.append(band_from_dict(d, f"band set JSON: band {k}"))
        return cls(tuple(out))

    def to_json(self) -> str:
        """The bands as JSON, a list of ``{"center_nm", "fwhm_nm"}`` (and ``"response"`` for a measured curve:
        ``Band.to_dict``) in band order: for manifests and ONNX metadata; ``from_json`` reads it back."""
        return json.dumps([b.to_dict() for b in self.bands])

    def __len__(self) -> int:
        return len(self.bands)

    def __iter__(self) -> Iterator[Band]:
        return iter(self.bands)

    def __getitem__(self, i: int) -> Band:
        return self.bands[i]

    @property
    def centers(self) -> tuple[float, ...]:
        """The band centres, nm."""
        return tuple(b.center_nm for b in self.bands)

    @property
    def columns(self) -> tuple[str, ...]:
        """The dataset column of each band: ``r`` and its label (``r544``); ``ValueError`` if two coincide."""
        cols = tuple(f"r{b.label}" for b in self.bands)
        if len(set(cols)) < len(cols):
            raise ValueError(f"bands {', '.join(self.labels)} nm: two share a column name; use distinct centres")
        return cols

    @property
    def labels(self) -> tuple[str, ...]:
        """``Band.label`` of each band."""
        return tuple(b.label for b in self.bands)

    def index(self, nm: float, tol_nm: float = BAND_MATCH_NM) -> int:
        """The position of the band centred nearest ``nm``, within ``tol_nm``; ``ValueError`` if none is."""
        d = [abs(c - nm) for c in self.centers]
        k = min(range(len(d)), key=d.__getitem__)
        if not d[k] <= tol_nm:
            raise ValueError(f"no band within {tol_nm:g} nm of {nm:g} nm (the bands: {', '.join(self.labels)} nm)")
        return k


#: The thesis's detection system: the ``INDEX_BANDS_NM`` bands, monochromatic, as a ``BandSet``.
INDEX_BANDS = BandSet.of(INDEX_BANDS_NM)
#: ``INDEX_BANDS``' bands as a tuple: the bands of every command without ``--bands``.
DEFAULT_BANDS: tuple[Band, ...] = INDEX_BANDS.bands


#: the ``lut`` table's coordinates by name, kept in its checkpoints and graphs (``detectors.lut.grid``): each band's
#: float32 bit pattern read as an integer, a piecewise-linear log2 of the reflectance in units of 2^-23 octave. Axis 0
#: is the last band's (the brightness), axis k (1 to n - 1) band k - 1's less band k's (the log ratio of neighbouring
#: bands); each axis is cut into cells of 2^shift units. A table built on other coordinates is refused
LUT_COORDINATES = "float-bits:ref-band+ratios-towards-ref"


def ratio_pairs(n: int, ref: int = -1) -> tuple[list[int], list[int]]:
    """The ``lut`` table's axes over n bands with reference band ``ref``: each axis's band and the band it is
    divided by (its neighbour towards ``ref``), axis 0 first (the reference itself, the brightness: its own index).
    ``ValueError`` for fewer than 2 bands.

    >>> ratio_pairs(4, 2)
    ([2, 0, 1, 3], [2, 1, 2, 2])
    """
    if n < 2:
        raise ValueError(f"a lookup table needs at least 2 bands, got {n}")
    ref = ref % n
    others = [i for i in range(n) if i != ref]
    return [ref, *others], [ref, *[i + 1 if i < ref else i - 1 for i in others]]


def parse_bands(text: str, within: tuple[float, float] | None = None) -> tuple[Band, ...]:
    """The bands of a ``--bands`` list as a tuple: ``BandSet.parse`` (``within``: its default range).

    >>> [(b.center_nm, b.fwhm_nm) for b in parse_bands("544,1080/20")]
    [(544.0, 0.0), (1080.0, 20.0)]
    """
    return BandSet.parse(text, within).bands


def check_ascending(bands: Sequence[Band], what: str = "bands") -> None:
    """``ValueError`` unless the band centres strictly ascend: per-band values given as four numbers (material
    spectra, sensor settings: ``per_band``) are read in band order, so a reversed or repeated band would take
    another band's value."""
    c = [b.center_nm for b in bands]
    if any(b <= a for a, b in zip(c, c[1:])):
        raise ValueError(f"{what} must list band centres in strictly ascending order, got {', '.join(f'{x:g}' for x in c)}")
    same = [(a, b) for a, b in zip(bands, bands[1:]) if a.label == b.label]
    if same:
        a, b = same[0]
        raise ValueError(f"{what}: bands {a.center_nm!r} and {b.center_nm!r} nm are both written as {a.label} nm "
                         f"(six significant digits: their images and columns would collide): use distinct centres")


def response_weights(grid: Sequence[float] | np.ndarray, center_nm: float, fwhm_nm: float,
                     response: tuple[Sequence[float], Sequence[float]] | None = None) -> np.ndarray:
    """The band response model, numpy only (float64), the one place its formula is written: the weights
    ``(n_grid,)``, summing to 1, that average a spectrum sampled on the increasing wavelengths ``grid`` (nm) over the
    band (``center_nm``, ``fwhm_nm``). A Gaussian band (``FWHM_TO_SIGMA``) truncated at its support (centre +-
    ``SUPPORT_FWHM`` FWHM) with trapezoid quadrature on the grid; a monochromatic band (fwhm 0) the
    linear-interpolation weights at its centre; a measured curve (``response``: ``Band.response``) interpolated
    linearly onto the grid (0 outside its table), with trapezoid quadrature. ``response_matrix`` (torch, the renderer) and
    ``onboard.band_plan`` (numpy, a camera's cube) both use it. ``ValueError`` when the grid is too coarse for the
    band; the caller checks that the grid covers the band's support.

    >>> [round(float(w), 3) for w in response_weights([540.0, 550.0], 544.0, 0.0)]
    [0.6, 0.4]
    """
    import numpy as np

    g = np.asarray(grid, dtype=np.float64)
    if g.size == 1:
        return np.ones(1)
    if response is not None:
        shape = np.interp(g, np.asarray(response[0], dtype=np.float64), np.asarray(response[1], dtype=np.float64),
                          left=0.0, right=0.0)
        w = shape * _trapezoid(g)
        if not w.sum() > 0:
            raise ValueError(f"grid too coarse for the response curve of band {center_nm:g} nm")
        return w / w.sum()
    if fwhm_nm == 0:
        i = int(np.clip(np.searchsorted(g, center_nm, side="right"), 1, g.size - 1))
        t = (center_nm - g[i - 1]) / (g[i] - g[i - 1])
        w = np.zeros_like(g)
        w[i - 1] = 1 - t
        w[i] = t
        return w
    sigma = fwhm_nm * FWHM_TO_SIGMA
    s_lo, s_hi = center_nm - SUPPORT_FWHM * fwhm_nm, center_nm + SUPPORT_FWHM * fwhm_nm
    gauss = np.where((g >= s_lo) & (g <= s_hi), np.exp(-0.5 * ((g - center_nm) / sigma) ** 2), 0.0)
    w = gauss * _trapezoid(g)
    if not w.sum() > 0:
        raise ValueError(f"grid too coarse for band {center_nm:g}/{fwhm_nm:g} nm")
    return w / w.sum()


def _trapezoid(g: np.ndarray) -> np.ndarray:
    """Trapezoid quadrature weights on the increasing grid ``g``."""
    import numpy as np

    trap = np.zeros_like(g)
    trap[:-1] += 0.5 * np.diff(g)
    trap[1:] += 0.5 * np.diff(g)
    return trap


def response_matrix(grid: TensorLike, bands: Sequence[Band]) -> torch.Tensor:
    """Weights ``(n_grid, n_bands)``, each column summing to 1, so that ``spectrum @ W`` gives band values.

    ``grid`` is an increasing 1-D wavelength tensor (nm). Gaussian bands use trapezoid quadrature on the
    grid; monochromatic bands use linear-interpolation weights (``response_weights``, computed in float64 and
    cast to the grid's dtype and device). Raises ``ValueError`` if a band's support is not inside the grid.
    """
    import numpy as np
    import torch

    from ._checks import as_tensor

    grid = as_tensor(grid)
    if grid.ndim != 1 or grid.numel() < 1:
        raise ValueError("grid must be a 1-D wavelength tensor")
    g = grid.detach().cpu().to(torch.float64).numpy()
    lo, hi = float(g[0]), float(g[-1])
    cols = []
    for b in bands:
        s_lo, s_hi = b.support
        if s_lo < lo - 1e-9 or s_hi > hi + 1e-9:
            raise ValueError(
                f"band {b.describe()} nm needs wavelengths {s_lo:g}..{s_hi:g} nm;"
                f" the grid covers only {lo:g}..{hi:g} nm"
            )
        cols.append(response_weights(g, b.center_nm, b.fwhm_nm, b.response))
    return torch.as_tensor(np.stack(cols, axis=-1), dtype=grid.dtype, device=grid.device)


def band_integrate(values: torch.Tensor, grid: TensorLike, bands: Sequence[Band]) -> torch.Tensor:
    """Band values ``(..., n_bands)`` of spectra ``values`` ``(..., n_grid)`` sampled on ``grid``."""
    from ._checks import as_tensor

    bands = as_bands(bands)
    grid = as_tensor(grid, like=values)
    if values.shape[-1] != grid.shape[-1]:
        raise ValueError(f"values' last axis ({values.shape[-1]}) must match the grid length ({grid.shape[-1]})")
    return values @ response_matrix(grid, bands)


def band_sampling(bands: Sequence[Band], step_nm: float = 1.0, dtype: torch.dtype | None = None,
                  device: torch.device | str | None = None,
                  within: tuple[float, float] | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """A wavelength grid that samples every band and the matrix that averages it back to bands: evaluate a
    model on ``grid`` and multiply by ``W`` to get band values. Monochromatic bands contribute their centre
    only; a Gaussian band its support sampled every ``step_nm`` (at least 9 points).

    Args:
        bands: the bands (anything ``as_bands`` takes).
        step_nm: grid step inside a Gaussian band's support, nm.
        dtype, device: of the outputs (default: torch's default dtype, the CPU).
        within: ``(lo, hi)`` nm that every band's response must lie in; default the skin model's 400-1700 nm.
            Checked, like the grid size (at most ``MAX_GRID_POINTS`` wavelengths), before anything is allocated.

    Shape:
        ``grid`` (G,), increasing; ``W`` (G, n_bands), each column summing to 1.

    Returns:
        ``(grid, W)``.

    >>> grid, W = band_sampling([Band(544.0), Band(1080.0, 20.0)])
    >>> tuple(grid.shape), tuple(W.shape), [round(float(x), 4) for x in W.sum(0)]
    ((62,), (62, 2), [1.0, 1.0])
    """
    import torch

    bands = as_bands(bands)
    if isinstance(step_nm, bool) or not isinstance(step_nm, (int, float)) or not (
            math.isfinite(step_nm) and step_nm > 0):
        raise ValueError(f"step_nm must be a positive finite number of nm, got {step_nm!r}")
    lo, hi = MODEL_RANGE_NM if within is None else within
    counts = []
    for b in bands:
        check_band_within(b, lo, hi)
        span = (b.support[1] - b.support[0]) / step_nm
        counts.append(1 if b.fwhm_nm == 0 else (max(math.ceil(span), 8) + 1 if span <= MAX_GRID_POINTS else span))
    if sum(counts) > MAX_GRID_POINTS:
        raise ValueError(f"band sampling at {step_nm:g} nm steps would need {sum(counts):.3g} wavelengths; at most "
                         f"{MAX_GRID_POINTS} (use fewer or narrower bands, or a larger step)")
    if sum(counts) * len(bands) > 16 * MAX_GRID_POINTS:
        raise ValueError(f"band sampling of {len(bands)} bands would need a {sum(counts):.3g} x {len(bands)} weight "
                         f"matrix; at most {16 * MAX_GRID_POINTS} entries (use fewer or narrower bands)")
    pts: list[float] = []
    for b, n in zip(bands, counts):
        if b.fwhm_nm == 0:
            pts.append(b.center_nm)
        else:
            s_lo, s_hi = b.support
            pts.extend(torch.linspace(s_lo, s_hi, int(n), dtype=torch.float64).tolist())
    uniq = sorted(set(round(p, 9) for p in pts))
    grid = torch.tensor(uniq, dtype=dtype or torch.get_default_dtype(), device=device)
    cols = []
    for b in bands:  # per-band weights on the sub-grid belonging to that band only
        if b.fwhm_nm == 0:
            w = (torch.abs(grid - b.center_nm) < 1e-6).to(grid.dtype)
        else:
            s_lo, s_hi = b.support
            sel = (grid >= s_lo - 1e-9) & (grid <= s_hi + 1e-9)
            sub = grid[sel]
            w = torch.zeros_like(grid)
            w[sel] = response_matrix(sub, [b])[:, 0]
        cols.append(w / w.sum())
    return grid, torch.stack(cols, dim=-1)


#: the keys of a spectrum given at wavelengths (``at_wavelengths``), a per-band setting that ``per_band``
#: interpolates in wavelength for any bands
SPECTRUM_KEYS = ("wavelengths_nm", "values")


def at_wavelengths(values: Sequence[float], wavelengths_nm: Sequence[float] = INDEX_BANDS_NM) -> dict[str, list[float]]:
    """A per-band setting given as a spectrum at ``wavelengths_nm`` (default the ``INDEX_BANDS_NM``), as JSON data:
    ``{"wavelengths_nm": [...], "values": [...]}``. ``per_band`` interpolates it linearly in wavelength for any
    bands, whatever their number, so it means the same under every ``--bands``: the built-in four-value spectra
    (the default scene's clothing and ground, the sensor's defaults) are written this way. ``ValueError`` unless
    the wavelengths strictly ascend and there is one value for each.

    >>> at_wavelengths([0.12, 0.10, 0.35, 0.30])
    {'wavelengths_nm': [544.0, 633.0, 1080.0, 1580.0], 'values': [0.12, 0.1, 0.35, 0.3]}
    """
    spec = {"wavelengths_nm": [float(w) for w in wavelengths_nm], "values": [float(v) for v in values]}
    _spectrum_nodes(spec, "a spectrum")
    return spec


def spectrum_at(values: PerBand, wavelengths_nm: Sequence[float], what: str) -> list[float] | None:
    """A per-band setting given as a spectrum at wavelengths (``at_wavelengths``), interpolated linearly at
    ``wavelengths_nm`` (held constant outside its nodes); None for the other forms (a number, one value per band).

    >>> spectrum_at(at_wavelengths([0.1, 0.3], [500.0, 700.0]), [500.0, 600.0, 800.0], "reflectance")
    [0.1, 0.2, 0.3]
    >>> spectrum_at(0.5, [500.0], "reflectance") is None
    True
    """
    import numpy as np

    if not isinstance(values, Mapping):
        return None
    wl, vals = _spectrum_nodes(values, what)
    return [float(v) for v in np.interp(np.asarray(wavelengths_nm, dtype=np.float64), wl, vals)]


def _spectrum_nodes(spec: object, what: str) -> tuple[list[float], list[float]]:
    """(wavelengths, values) of a spectrum given at wavelengths (``at_wavelengths``); ``ValueError`` naming
    ``what`` when it is malformed."""
    if not isinstance(spec, Mapping) or set(spec) != set(SPECTRUM_KEYS):
        raise ValueError(f"{what} given at wavelengths needs exactly the keys {' and '.join(SPECTRUM_KEYS)}, got "
                         f"{sorted(spec) if isinstance(spec, Mapping) else type(spec).__name__}")
    try:
        wl, vals = ([float(x) for x in spec[k]] for k in SPECTRUM_KEYS)
    except (TypeError, ValueError):
        raise ValueError(f"{what} given at wavelengths needs lists of numbers, got {spec!r}") from None
    if not wl or len(wl) != len(vals):
        raise ValueError(f"{what} given at wavelengths needs one value for each of at least one wavelength, got "
                         f"{len(wl)} wavelengths and {len(vals)} values")
    if not all(math.isfinite(w) and w > 0 for w in wl) or any(b <= a for a, b in zip(wl, wl[1:])):
        raise ValueError(f"{what} given at wavelengths needs positive wavelengths (nm) in strictly ascending order, "
                         f"got {wl}")
    return wl, vals


def setting_values(values: PerBand, what: str = "a per-band setting") -> list[float]:
    """The numbers of a per-band setting (``per_band``'s ``values``), for range checks: the one number, the list,
    or a spectrum's values.

    >>> setting_values(at_wavelengths([0.1, 0.2, 0.3, 0.4])), setting_values(0.5)
    ([0.1, 0.2, 0.3, 0.4], [0.5])
    """
    if isinstance(values, Mapping):
        return _spectrum_nodes(values, what)[1]
    if isinstance(values, (list, tuple)):
        return [float(v) for v in values]
    return [float(values)]  # type: ignore[arg-type]  # a number, or anything float() takes


def per_band(values: PerBand, bands: Sequence[Band], what: str) -> list[float]:
    """One value per band from a per-band setting (e.g. a sensor's path radiance, a material's reflectance).

    Args:
        values: one of

            - one number, for every band;
            - a spectrum given at wavelengths (``at_wavelengths``: ``{"wavelengths_nm": [...], "values": [...]}``),
              interpolated linearly in wavelength (held constant outside) at each band centre, whatever the number
              of bands: how the built-in four-value spectra are given, at the ``INDEX_BANDS_NM``;
            - a list of one value per band, taken in band order;
            - for another number of bands than four, a list of four values at the ``INDEX_BANDS_NM`` wavelengths
              (544, 633, 1080, 1580 nm), interpolated like a spectrum.

        bands: the bands.
        what: the quantity's name, for the error message.

    Returns:
        ``len(bands)`` floats; ``ValueError`` for any other number of values or a malformed spectrum.

    Four bands that are not the index bands take a built-in spectrum by wavelength, a list of four by position:

    >>> four = [Band(450.0), Band(550.0), Band(650.0), Band(750.0)]
    >>> [round(x, 4) for x in per_band(at_wavelengths([0.1, 0.2, 0.3, 0.4]), four, "path radiance")]
    [0.1, 0.1067, 0.2038, 0.2262]
    >>> per_band([0.1, 0.2, 0.3, 0.4], four, "path radiance")
    [0.1, 0.2, 0.3, 0.4]
    >>> [round(x, 4) for x in per_band([0.1, 0.2, 0.3, 0.4], [Band(600.0), Band(1300.0)], "path radiance")]
    [0.1629, 0.344]
    """
    import numpy as np

    n = len(bands)
    centres = [b.center_nm for b in bands]
    if isinstance(values, Mapping):
        wl, vals = _spectrum_nodes(values, what)
        return [float(v) for v in np.interp(centres, wl, vals)]
    vals = setting_values(values, what)
    if not isinstance(values, (list, tuple)):
        vals = vals * n
    if len(vals) == n:
        return vals
    if len(vals) == len(INDEX_BANDS_NM):
        return [float(v) for v in np.interp(centres, INDEX_BANDS_NM, vals)]
    raise ValueError(f"{what} needs one value, one per band ({n}), four (at "
                     f"{', '.join(f'{c:g}' for c in INDEX_BANDS_NM)} nm, interpolated) or a spectrum at wavelengths "
                     f"(bands.at_wavelengths), got {len(vals)}")
