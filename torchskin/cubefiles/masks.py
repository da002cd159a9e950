"""Masks written rows by rows: a greyscale PNG (``PngRows``, read back by ``read_png_gray``) or a uint8 GeoTIFF
(``TiffMaskRows``)."""

from __future__ import annotations

import contextlib
import struct
import zlib
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..io import (
    StrPath,
    atomic_path,
)
from .common import MappedOutput, _need, release_pages
from .tiff import tiff_extratags


class PngRows:
    """A greyscale 8-bit PNG of ``H`` x ``W`` written rows by rows (``write_rows`` of uint8 (rows, W), in order)
    through one zlib stream into a temporary file, renamed on ``close()``: no whole image in memory."""

    def __init__(self, path: StrPath, H: int, W: int):
        self.H, self.W, self.rows = int(H), int(W), 0
        self._ctx = atomic_path(path)
        self._tmp = self._ctx.__enter__()
        self._fh = open(self._tmp, "wb")  # noqa: SIM115 - closed by close()/abort()
        self._z = zlib.compressobj(6)
        self._fh.write(b"\x89PNG\r\n\x1a\n" + self._chunk(b"IHDR", struct.pack(">IIBBBBB", W, H, 8, 0, 0, 0, 0)))

    @staticmethod
    def _chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    def write_rows(self, rows: np.ndarray) -> None:
        a = np.ascontiguousarray(rows, dtype=np.uint8)
        raw = np.concatenate([np.zeros((a.shape[0], 1), np.uint8), a], 1).tobytes()  # filter 0 before each row
        data = self._z.compress(raw)
        if data:
            self._fh.write(self._chunk(b"IDAT", data))
        self.rows += a.shape[0]

    def close(self) -> None:
        if self.rows != self.H:
            raise RuntimeError(f"PNG got {self.rows} rows of {self.H}")
        self._fh.write(self._chunk(b"IDAT", self._z.flush()) + self._chunk(b"IEND", b""))
        self._fh.close()
        self._ctx.__exit__(None, None, None)

    def abort(self, exc: BaseException | None = None) -> None:
        self._fh.close()
        e = exc or RuntimeError("aborted")
        with contextlib.suppress(BaseException):
            self._ctx.__exit__(type(e), e, e.__traceback__)


class TiffMaskRows(MappedOutput):
    """A uint8 (H, W) mask GeoTIFF (skin 255) with ``geotags``, written rows by rows into a memory-mapped
    temporary file, renamed on ``close()``."""

    def __init__(self, path: StrPath, H: int, W: int, geotags: Sequence = ()):
        tifffile = _need("tifffile", f"writing {str(path)!r} (GeoTIFF)")
        self.H = int(H)
        self._ctx = atomic_path(path)
        tmp = self._ctx.__enter__()
        try:
            self._mm = tifffile.memmap(str(tmp), shape=(H, W), dtype=np.uint8, photometric="minisblack",
                                       extratags=tiff_extratags(None, None, geotags))
        except BaseException as e:
            self._ctx.__exit__(type(e), e, e.__traceback__)
            raise
        self.rows = 0

    def write_rows(self, rows: np.ndarray) -> None:
        self._mm[self.rows:self.rows + rows.shape[0]] = rows
        self.rows += rows.shape[0]
        release_pages(self._mm)

    def close(self) -> None:
        self._mm.flush()
        del self._mm
        self._ctx.__exit__(None, None, None)


def read_png_gray(path: StrPath) -> np.ndarray:
    """An 8-bit greyscale PNG written by ``PngRows`` or ``io.write_png`` as a uint8 (H, W) array (for tests and
    comparisons; filter type 0 only)."""
    data = Path(path).read_bytes()
    pos, idat, w, h = 8, [], 0, 0
    while pos < len(data):
        n, tag = struct.unpack(">I4s", data[pos:pos + 8])
        body = data[pos + 8:pos + 8 + n]
        if tag == b"IHDR":
            w, h = struct.unpack(">II", body[:8])
        elif tag == b"IDAT":
            idat.append(body)
        pos += 12 + n
    raw = np.frombuffer(zlib.decompress(b"".join(idat)), np.uint8).reshape(h, w + 1)
    return raw[:, 1:]
