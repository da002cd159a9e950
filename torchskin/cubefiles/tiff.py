"""GeoTIFF cubes through tifffile: the wavelengths, scale and offset of the GDAL_METADATA tag, a multi-band
GeoTIFF as a ``CubeFile`` (``_open_tiff``), and the tags written with a cube or a mask."""

from __future__ import annotations

import contextlib
from collections.abc import Sequence
from pathlib import Path
from xml.sax.saxutils import escape

import numpy as np

from .common import GDAL_METADATA_TAG, GEOTIFF_TAGS, QUANTITY_UNITS, CubeFile, _need, to_nm, units_scale


def _gdal_items(xml: str) -> tuple[dict[str, str], dict[int, dict[str, str]]]:
    """GDAL_METADATA's items: (dataset-level {name: value}, {band index: {name: value}}), names lower case."""
    import xml.etree.ElementTree as ET

    root = ET.fromstring(xml.strip().strip("\x00"))
    top: dict[str, str] = {}
    per: dict[int, dict[str, str]] = {}
    for item in root.iter("Item"):
        name = (item.get("name") or "").lower()
        text = (item.text or "").strip()
        if item.get("sample") is None:
            top[name] = text
        else:
            per.setdefault(int(item.get("sample") or 0), {})[name] = text
    return top, per


def _tiff_scale_offset(xml: str | None, nb: int, where: str) -> tuple[list[float] | None, list[float] | None]:
    """GDAL_METADATA's per-band ``SCALE`` and ``OFFSET`` (value = stored x SCALE + OFFSET); None when no band gives
    one (a band without one: 1 and 0)."""
    if not xml:
        return None, None
    with contextlib.suppress(Exception):  # a malformed tag is refused by _tiff_wavelengths
        _, per = _gdal_items(xml)
        out: list[list[float] | None] = []
        for name, default in (("scale", 1.0), ("offset", 0.0)):
            if not any(name in per.get(b, {}) for b in range(nb)):
                out.append(None)
                continue
            try:
                out.append([float(per.get(b, {}).get(name, default)) for b in range(nb)])
            except ValueError:
                raise ValueError(f"{where}: a band's {name.upper()} in GDAL_METADATA is not a number") from None
        return out[0], out[1]
    return None, None


def _tiff_wavelengths(xml: str | None, nb: int, where: str) -> tuple[list[float] | None, list[float] | None]:
    """Band centres and FWHM (nm) from a GDAL_METADATA tag; (None, None) when it gives none."""
    if not xml:
        return None, None
    try:
        top, per = _gdal_items(xml)
    except Exception:  # noqa: BLE001 - malformed XML: as if there were no metadata
        raise ValueError(f"{where}: its GDAL_METADATA tag is not valid XML") from None
    centres, fwhm = [], []
    for b in range(nb):
        d = per.get(b, {})
        try:
            if "wavelength" in d:
                s = units_scale(d.get("wavelength_units", top.get("wavelength_units")), where)
                centres.append((float(d["wavelength"]), s))
                fwhm.append(float(d["fwhm"]) * (s or 1.0) if "fwhm" in d else None)
            elif "central_wavelength_um" in d:
                centres.append((float(d["central_wavelength_um"]), 1000.0))
                fwhm.append(float(d["fwhm_um"]) * 1000.0 if "fwhm_um" in d else None)
            else:
                return None, None
        except ValueError:
            raise ValueError(f"{where}: band {b + 1}'s wavelength in GDAL_METADATA is not a number") from None
    scales = {s for _, s in centres}
    if None in scales and len(scales) > 1:
        raise ValueError(f"{where}: some bands declare their wavelength units and others do not")
    if None in scales:
        bands = to_nm([c for c, _ in centres], None, where)
    else:  # each band in its declared unit (bands may declare different ones)
        bands = to_nm([c * (s or 1.0) for c, s in centres], "nm", where)
    return bands, (None if any(f is None for f in fwhm) else [float(f) for f in fwhm if f is not None])


def _open_tiff(p: Path, option: str, max_megapixels: float, need_wavelengths: bool = True) -> CubeFile:
    from ..errors import one_line

    tifffile = _need("tifffile", f"{option} {str(p)!r} (GeoTIFF)")
    where = f"{option} {str(p)!r}"
    try:
        with tifffile.TiffFile(str(p)) as tif:
            page = tif.pages[0]
            series = tif.series[0]
            axes, shape, dtype = series.axes, tuple(series.shape), np.dtype(series.dtype)
            xml = page.tags[GDAL_METADATA_TAG].value if GDAL_METADATA_TAG in page.tags else None
            geotags = [(c, int(page.tags[c].dtype), page.tags[c].count, page.tags[c].value)
                       for c in GEOTIFF_TAGS if c in page.tags]
            compressed = int(page.compression) != 1
    except Exception as e:  # noqa: BLE001 - tifffile raises its own types for a bad file
        raise ValueError(f"cannot read {where}: {one_line(e)}") from None
    if dtype.kind not in "fiu":
        raise ValueError(f"{where} must hold real numbers, got dtype {dtype}")
    if len(shape) == 2:
        axes, shape = "S" + axes, (1, *shape)
    if len(shape) != 3 or axes[-2:] not in ("YX", "XS") and axes[1:] != "YX":
        raise ValueError(f"{where}: expected one multi-band image (bands, rows, columns), got axes {axes!r} "
                         f"shape {shape}")
    lay = "yxb" if axes.endswith("S") and axes[0] == "Y" else "byx"
    nb = shape[lay.index("b")]
    bands, fwhm = _tiff_wavelengths(xml, nb, where)
    scale, offset = _tiff_scale_offset(xml, nb, where)
    if bands is None and need_wavelengths:
        raise ValueError(f"{where} gives no band wavelengths: expected GDAL_METADATA items 'wavelength' (and "
                         "'wavelength_units') for every band")
    data = None
    streaming = not compressed
    if streaming:
        try:
            data = tifffile.memmap(str(p), mode="r")
        except Exception:  # noqa: BLE001 - not memory-mappable (tiles, strips apart): read whole
            streaming = False
    if data is None:
        mp = shape[lay.index("y")] * shape[lay.index("x")] / 1e6
        if mp > max_megapixels:
            raise ValueError(f"{where} is compressed (read whole, not streamed) and its frames are {mp:.1f} "
                             f"megapixels, above the cap of {max_megapixels:g} (--max-megapixels raises it; or "
                             "write it uncompressed)")
        try:
            data = tifffile.imread(str(p))
        except Exception as e:  # noqa: BLE001
            raise ValueError(f"cannot read {where}: {one_line(e)}") from None
    data = np.asarray(data).reshape(shape)
    return CubeFile(p, "tiff", data, lay, bands, fwhm, option, geotags=geotags, streaming=streaming, scale=scale,
                    offset=offset)


def gdal_metadata_xml(bands: Sequence[float] | None, fwhm: Sequence[float] | None,
                      quantity: str | None = None, units: str | None = None) -> str | None:
    """The GDAL_METADATA tag text with each band's ``wavelength``, ``wavelength_units`` (nm) and ``fwhm`` items,
    as GDAL's ENVI driver writes them, and the values' ``units`` as each band's unit type (None without
    wavelengths)."""
    if bands is None:
        return None
    items = [] if quantity is None else [f'<Item name="quantity">{escape(quantity)}</Item>']
    if units is not None:
        items.append(f'<Item name="units">{escape(units)}</Item>')
    for i, b in enumerate(bands):
        items.append(f'<Item name="DESCRIPTION" sample="{i}" role="description">{b:g} nm</Item>')
        if units is not None:
            items.append(f'<Item name="UNITTYPE" sample="{i}" role="unittype">{escape(units)}</Item>')
        items.append(f'<Item name="wavelength" sample="{i}">{b:g}</Item>')
        items.append(f'<Item name="wavelength_units" sample="{i}">Nanometers</Item>')
        if fwhm is not None:
            items.append(f'<Item name="fwhm" sample="{i}">{fwhm[i]:g}</Item>')
    return "<GDALMetadata>" + "".join(items) + "</GDALMetadata>"


def tiff_extratags(bands: Sequence[float] | None, fwhm: Sequence[float] | None, geotags: Sequence = (),
                   quantity: str | None = None) -> list:
    """tifffile ``extratags``: the input's geotags and the GDAL_METADATA wavelengths (and ``quantity``'s units,
    ``QUANTITY_UNITS``)."""
    tags = [(c, dt, n, v, True) for c, dt, n, v in geotags]
    xml = gdal_metadata_xml(bands, fwhm, quantity, QUANTITY_UNITS.get(quantity or ""))
    if xml is not None:
        tags.append((GDAL_METADATA_TAG, 2, 0, xml, True))
    return tags
