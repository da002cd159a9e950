"""Crash-safe file writing (write to a temporary name in the target folder, fsync, then rename) and the one
reading of ``.npy`` headers and the dtype rule of the cubes commands take (``as_float32``; the reader is
``onboard.load_cube``). numpy only."""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import numpy as np
    from numpy.typing import ArrayLike

#: a file path as the writers take it: a ``str`` or any ``os.PathLike[str]`` (``pathlib.Path``)
StrPath = str | os.PathLike[str]


@contextlib.contextmanager
def atomic_path(path: StrPath, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success it is fsync'd and renamed onto ``path``.

    On an exception the temporary file is removed and ``path`` is left untouched.

    Args:
        path: the file to write; its folder must exist (``ValueError`` otherwise).
        suffix: the temporary file's suffix (default: ``path``'s own, so writers that pick a format by the
            name, e.g. ``savefig``, see the right one).

    Yields:
        The temporary path to write to.

    >>> from tempfile import TemporaryDirectory
    >>> with TemporaryDirectory() as d:
    ...     with atomic_path(Path(d) / "table.csv") as tmp:
    ...         _ = tmp.write_text("a,b\\n")
    ...     print(sorted(p.name for p in Path(d).iterdir()))
    ['table.csv']
    """
    path = Path(path)
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        raise ValueError(f"output folder {str(parent)!r} does not exist")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix if suffix is not None else path.suffix,
                               dir=parent)
    os.close(fd)
    try:
        yield Path(tmp)
        with open(tmp, "rb") as fh:
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp creates 0600; give the file the usual permissions
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def write_text(path: StrPath, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically: a crash leaves the old file or the new one, never half of it.

    Args:
        path: the file to write; its folder must exist.
        text: the whole content.

    >>> from tempfile import TemporaryDirectory
    >>> with TemporaryDirectory() as d:
    ...     write_text(Path(d) / "note.txt", "skin\\n")
    ...     print(repr((Path(d) / "note.txt").read_text()), len(list(Path(d).iterdir())))
    'skin\\n' 1
    """
    with atomic_path(path) as tmp:
        Path(tmp).write_text(text, encoding="utf-8")


def write_bytes(path: StrPath, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (see ``write_text``).

    Args:
        path: the file to write; its folder must exist.
        data: the whole content.
    """
    with atomic_path(path) as tmp:
        Path(tmp).write_bytes(data)


def save_npy(path: StrPath, array: ArrayLike, suffix: str = ".npy") -> None:
    """``numpy.save`` to ``path`` exactly (no ``.npy`` appended), written atomically.

    Args:
        path: the file to write; its folder must exist.
        array: anything ``numpy.save`` takes.
        suffix: the temporary file's suffix.
    """
    import numpy as np

    with atomic_path(path, suffix=suffix) as tmp:
        with open(tmp, "wb") as fh:
            np.save(fh, array)


def save_torch(path: StrPath, obj: object) -> None:
    """``torch.save`` written atomically and serialised through a buffer, so the archive does not carry the
    temporary file's random name: the same object gives the same bytes.

    Args:
        path: the file to write; its folder must exist.
        obj: anything ``torch.save`` takes (a checkpoint dict).
    """
    import io

    import torch

    buf = io.BytesIO()
    torch.save(obj, buf)
    write_bytes(path, buf.getvalue())


def write_png(path: StrPath, image: ArrayLike) -> None:
    """An 8-bit PNG of a uint8 array, (H, W) greyscale or (H, W, 3) RGB, one PNG pixel per element (stdlib
    zlib, no imaging library), written atomically.

    Args:
        path: the file to write; its folder must exist.
        image: (H, W) or (H, W, 3) values, converted to uint8; ``ValueError`` for any other shape.

    >>> from tempfile import TemporaryDirectory
    >>> with TemporaryDirectory() as d:
    ...     write_png(Path(d) / "mask.png", [[0, 255], [255, 0]])
    ...     print((Path(d) / "mask.png").read_bytes()[:8])
    b'\\x89PNG\\r\\n\\x1a\\n'
    """
    import struct
    import zlib

    import numpy as np

    a = np.ascontiguousarray(image, dtype=np.uint8)
    if a.ndim not in (2, 3) or (a.ndim == 3 and a.shape[2] != 3):
        raise ValueError(f"a PNG image must be (H, W) or (H, W, 3), got shape {a.shape}")
    h, w = a.shape[:2]
    raw = np.concatenate([np.zeros((h, 1), np.uint8), a.reshape(h, -1)], 1).tobytes()  # filter 0 before each row

    def chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    colour = 2 if a.ndim == 3 else 0
    write_bytes(path, b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, colour, 0, 0, 0))
                + chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b""))


# ------------------------------------------------------------------------------------------------ reading cubes
#: the largest frame (height x width, megapixels) a command makes or reads unless ``--max-megapixels`` raises it:
#: ``render`` and ``experiment`` check their resolution against it, ``detect`` and ``calibrate`` a cube's header
#: (``onboard.load_cube``) before they read its data
MAX_MEGAPIXELS = 16.0


def as_float32(x: ArrayLike) -> np.ndarray:
    """``x`` as native-byte-order float32, the one dtype the onboard runtime computes in: float64, float16,
    float32 of either byte order and integers (digital numbers, exact up to 2^24) convert alike; an array that
    already is native float32 comes back as it is (a memory map stays one). Raises ``ValueError`` for
    anything that does not hold real numbers (bool, complex, strings, objects).

    >>> import numpy as np
    >>> as_float32(np.array([1.5, 2.0], dtype=">f8")).dtype.str, as_float32(np.arange(3, dtype=np.uint16)).tolist()
    ('<f4', [0.0, 1.0, 2.0])
    """
    import numpy as np

    a = np.asarray(x)
    if a.dtype.kind not in "fiu":
        raise ValueError(f"must hold real numbers, got dtype {a.dtype}")
    if a.dtype == np.dtype(np.float32) and a.dtype.isnative:
        return a
    return a.astype(np.float32)


def npy_header(path: StrPath) -> tuple[tuple[int, ...], np.dtype]:
    """(shape, dtype) of a ``.npy`` file from its header alone (``numpy.lib.format``), reading none of its data.
    Raises ``ValueError`` when the file is not a ``.npy`` array."""
    import numpy as np

    with open(path, "rb") as fh:
        version = np.lib.format.read_magic(fh)
        if version == (1, 0):
            shape, _, dtype = np.lib.format.read_array_header_1_0(fh)
        elif version in ((2, 0), (3, 0)):  # 3.0 differs only in the header's text encoding
            shape, _, dtype = np.lib.format.read_array_header_2_0(fh)
        else:
            raise ValueError(f"unsupported .npy format version {version}")
    return tuple(shape), dtype


# ------------------------------------------------------------------------------------ a cube's wavelengths
#: the sidecar beside a ``.npy`` cube that says what its bands are: ``CUBE.npy`` -> ``CUBE.bands.json``
#: (``render`` writes one beside ``reflectance.npy`` and ``signal.npy``, ``calibrate`` beside its output;
#: ``detect`` and ``calibrate`` read it)
SIDECAR_SUFFIX = ".bands.json"


def sidecar_path(cube: StrPath) -> Path:
    """The wavelength sidecar of a cube file (``SIDECAR_SUFFIX``).

    >>> str(sidecar_path("frame/reflectance.npy"))
    'frame/reflectance.bands.json'
    """
    p = Path(cube)
    return p.with_name(p.stem + SIDECAR_SUFFIX)


def bands_sidecar_text(bands_nm: list[float], fwhm_nm: list[float] | None = None,
                       quantity: str = "reflectance") -> str:
    """The sidecar's JSON: band centres (and FWHM) in nm in the cube's band order (axis 0 of a (bands, H, W)
    cube, axis 1 of (frames, bands, H, W)) and what the values are ("reflectance" or "signal")."""
    import json

    doc: dict[str, object] = {"bands_nm": [float(b) for b in bands_nm], "units": "nm", "quantity": quantity}
    if fwhm_nm is not None:
        doc["fwhm_nm"] = [float(f) for f in fwhm_nm]
    return json.dumps(doc, indent=1)


def parse_band_list(text: str, option: str = "--bands") -> list[float]:
    """Band centres in nm, in the order given, of a cube's band list: ``bands.BandSet.parse`` with bands in any
    order and at any wavelength (a ``/FWHM`` is checked, then not used), then ``check_band_list``: distinct, in
    nm; ``ValueError`` naming ``option`` otherwise.

    >>> parse_band_list("1580, 544/20,1080,633")
    [1580.0, 544.0, 1080.0, 633.0]
    """
    from .bands import BandSet

    inf = float("inf")
    return check_band_list(list(BandSet.parse(text, (-inf, inf), ordered=False, option=option).centers), option)


def check_band_list(bands: list[float], where: str) -> list[float]:
    """``bands`` when they are distinct positive centres in nm; ``ValueError`` naming ``where`` otherwise (a band
    given twice, or centres that look like µm: all below 10)."""
    if not bands:
        raise ValueError(f"{where}: no band centres")
    if len(set(bands)) != len(bands):
        raise ValueError(f"{where}: a band is given twice ({', '.join(f'{b:g}' for b in bands)} nm)")
    if max(bands) < 10:
        raise ValueError(f"{where}: band centres {', '.join(f'{b:g}' for b in bands)} look like micrometres; "
                         "give them in nm")
    return bands


def read_bands_sidecar(cube: StrPath) -> list[float] | None:
    """The band centres (nm) of a cube from its sidecar (``sidecar_path``), or None when it has none;
    ``ValueError`` naming the sidecar when it cannot be read or does not hold distinct centres in nm."""
    import json

    p = sidecar_path(cube)
    if not p.is_file():
        return None
    try:
        doc = json.loads(p.read_text())
        bands = [float(b) for b in doc["bands_nm"]]
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise ValueError(f"cannot read the band sidecar {str(p)!r}: expected JSON with a 'bands_nm' list "
                         f"({type(e).__name__})") from None
    if doc.get("units", "nm") != "nm":
        raise ValueError(f"the band sidecar {str(p)!r} gives units {doc.get('units')!r}; expected 'nm'")
    return check_band_list(bands, f"the band sidecar {str(p)!r}")
