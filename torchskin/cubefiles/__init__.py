"""Cube files in and out, numpy only (no torch): the formats the field's cameras write and its tools open.

Reading (``open_cube``): a cube of one frame, bands x rows x columns, with its wavelengths, from

- ``.npy`` with the wavelength sidecar ``CUBE.bands.json`` (``io.read_bands_sidecar``), memory-mapped;
- ENVI: a ``.hdr`` header over a raw file (``CUBE.hdr`` + ``CUBE``, ``CUBE.img``, ``CUBE.dat``, ``CUBE.raw``,
  ...), opened through Spectral Python (``spectral.envi.open``) and memory-mapped: header ``wavelength``,
  ``wavelength units`` (nanometres; micrometres converted), ``fwhm``, ``interleave`` bsq/bil/bip, ``data type``,
  ``byte order`` and ``header offset``;
- multi-band GeoTIFF through tifffile: each band's wavelength from the GDAL_METADATA tag (the per-band items
  ``wavelength``, ``wavelength_units`` and ``fwhm`` that GDAL's ENVI driver and ``gdal_translate`` write, or GDAL's
  IMAGERY domain ``CENTRAL_WAVELENGTH_UM`` / ``FWHM_UM``), the georeferencing tags (``GEOTIFF_TAGS``) kept for the
  outputs. tifffile rather than rasterio: rasterio needs GDAL's binary wheels (tens of MB, and none for some
  platforms an onboard computer runs), while tifffile is pure Python over numpy, reads the tags byte for byte,
  and memory-maps uncompressed files: what streaming needs. A compressed GeoTIFF cannot be memory-mapped and
  is read whole, within ``--max-megapixels``.

``CubeFile.read_rows(r0, r1)`` reads only rows ``r0:r1`` (float32, bands x rows x W): ``onboard.detect_file`` and
``onboard.calibrate_file`` stream a frame larger than memory through it.

Writing (``CubeWriter``): ``.npy`` + sidecar, ENVI (``.hdr`` with ``wavelength units = Nanometers``,
``wavelength = {...}``, ``fwhm = {...}``, over a BSQ little-endian float32 ``.img``) or GeoTIFF (one page,
planar, float32, GDAL_METADATA per-band items, the input's geotags), tile by tile to temporary files that are
renamed on success (``io.atomic_path``); a mask as GeoTIFF (``write_mask_tiff``) or PNG (``PngRows``).

Spectral Python and tifffile are the ``formats`` extra: without them an ENVI or GeoTIFF file gets one line,
``pip install 'torchskin[formats]'``.

The package's modules: ``common`` (suffixes, units, ``CubeFile``), ``npy``, ``envi`` and ``tiff`` (each format's
reading and header), ``cubes`` (``open_cube``, ``CubeWriter``) and ``masks``; every name is importable from
``torchskin.cubefiles`` itself.
"""

from __future__ import annotations

from .common import CUBE_SUFFIXES as CUBE_SUFFIXES
from .common import ENVI_DATA_SUFFIXES as ENVI_DATA_SUFFIXES
from .common import ENVI_SUFFIXES as ENVI_SUFFIXES
from .common import FORMAT_HINT as FORMAT_HINT
from .common import GDAL_METADATA_TAG as GDAL_METADATA_TAG
from .common import GEOTIFF_TAGS as GEOTIFF_TAGS
from .common import NPY_SUFFIXES as NPY_SUFFIXES
from .common import QUANTITY_UNITS as QUANTITY_UNITS
from .common import TIFF_SUFFIXES as TIFF_SUFFIXES
from .common import UNITLESS_MIN_NM as UNITLESS_MIN_NM
from .common import WAVELENGTH_UNITS as WAVELENGTH_UNITS
from .common import WRITE_FORMATS as WRITE_FORMATS
from .common import CubeFile, cube_format, iter_row_tiles, release_pages, to_nm
from .common import _mapping as _mapping
from .common import _need as _need
from .common import units_scale as units_scale
from .cubes import CubeWriter, open_cube, output_path, write_cube
from .envi import _ENVI_DTYPES as _ENVI_DTYPES
from .envi import _open_envi as _open_envi
from .envi import envi_header_text, envi_paths
from .masks import PngRows, TiffMaskRows, read_png_gray
from .npy import _open_npy as _open_npy
from .npy import open_npy as open_npy
from .tiff import _gdal_items as _gdal_items
from .tiff import _open_tiff as _open_tiff
from .tiff import _tiff_scale_offset as _tiff_scale_offset
from .tiff import _tiff_wavelengths as _tiff_wavelengths
from .tiff import gdal_metadata_xml
from .tiff import tiff_extratags as tiff_extratags

__all__ = ["CubeFile", "CubeWriter", "PngRows", "TiffMaskRows", "cube_format", "envi_header_text", "envi_paths",
           "gdal_metadata_xml", "iter_row_tiles", "open_cube", "output_path", "read_png_gray", "release_pages", "to_nm",
           "write_cube"]
