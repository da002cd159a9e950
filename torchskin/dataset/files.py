"""Dataset folder files, without the renderer's imports: the folder's layout (manifest, shard and image names),
checksums, the manifest's checks, and reading the rows of frames whose ELM is valid (what training and evaluation
use): ``read_valid`` as a pyarrow table, ``read_rows`` as the schema's typed ``Rows`` (``dataset.schema``)."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..bands import INDEX_BANDS, BandSet
from ..io import StrPath
from .schema import READ_SCHEMAS, SCHEMA_VERSION, Rows, has_band

if TYPE_CHECKING:
    import pyarrow as pa
    import pyarrow.dataset as ds

MANIFEST = "_manifest.json"  # leading underscore: Parquet readers skip it when reading the folder
#: the renderer's revision for datasets: raised whenever the same config and seed render other bytes, so that
#: ``generate --resume`` does not keep shards of another revision (2: anny bodies in float64, camera rays and
#: facing tests and angles written out in a fixed order; 3: the light stage: SPECTRL2 sun, sky and ground-reflected
#: light, sky views, RTLSR ground and confusers; 4: ``elm_valid`` asks the panels to receive at least a third of the
#: light a surface facing the sun and sky does, ``render.elm.ELM_MAX_IRRADIANCE_RATIO``; 5: a band with a width
#: sees clothing, confuser and ground spectra averaged over its response, ``render.materials.band_reflectance``
#: (monochromatic bands, the default's, render the same bytes as 4); 1 or missing: before).
#: ``elm_valid``'s noise and gain checks (``render.elm.elm_line_valid``) change no row of the default datasets
RENDER_REVISION = 5
#: the subfolder of ``--images`` cubes, out of the way of Parquet readers of the dataset folder
IMAGES_DIR = "images"


def shard_name(k: int) -> str:
    """The file name of shard ``k``.

    >>> shard_name(7)
    'shard-00007.parquet'
    """
    return f"shard-{k:05d}.parquet"


def dataset_files(out: Path) -> list[Path]:
    """The files of a dataset folder and of its images subfolder."""
    files = [p for p in out.iterdir() if p.is_file()]
    if (out / IMAGES_DIR).is_dir():
        files += [p for p in (out / IMAGES_DIR).iterdir() if p.is_file()]
    return files


def intact(out: Path, entry: dict) -> bool:
    """Whether the file of a manifest entry (a shard's or its images') is there with the recorded size and SHA-256."""
    p = out / entry["name"]
    return p.is_file() and p.stat().st_size == entry["bytes"] and sha256_file(p) == entry["sha256"]


def sha256_file(path: StrPath) -> str:
    """The SHA-256 of a file's bytes, read in 1 MiB chunks.

    Args:
        path: the file.

    Returns:
        The hex digest (64 characters).
    """
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def manifest(data_dir: StrPath) -> dict[str, Any] | None:
    """The dataset's manifest, checked: every reader of a dataset (``open_dataset``, ``read_valid``, evaluate,
    train, ``dataset verify``) reads it here.

    Args:
        data_dir: the dataset folder.

    Returns:
        The parsed ``_manifest.json``, or None when the folder has none; a one-line ``ValueError`` naming the file
        when it is not a JSON object or its ``schema_version`` is not one this torchskin reads (``READ_SCHEMAS``:
        a dataset of a newer schema is not read as if it were this one's). A manifest without the key (not written
        by ``torchskin generate``) is read as it is.

    >>> import json, tempfile
    >>> d = tempfile.mkdtemp()
    >>> _ = (Path(d) / MANIFEST).write_text(json.dumps({"schema_version": 99}))
    >>> manifest(d)  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    ValueError: dataset manifest '.../_manifest.json' has schema_version 99; this torchskin reads schema versions 1 to 6 ...
    """
    p = Path(data_dir) / MANIFEST
    if not p.is_file():
        return None
    try:
        man = json.loads(p.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ValueError(f"dataset manifest {str(p)!r} is not valid JSON ({e}): not a torchskin dataset") from None
    if not isinstance(man, dict):
        raise ValueError(f"dataset manifest {str(p)!r} holds a JSON {type(man).__name__}, not an object: not a "
                         "torchskin dataset")
    v = man.get("schema_version")
    if "schema_version" in man and (type(v) is not int or v not in READ_SCHEMAS):
        why = ("a newer torchskin wrote it: upgrade torchskin to read it, or regenerate the dataset with this one"
               if type(v) is int and v > SCHEMA_VERSION else "not a schema torchskin writes")
        raise ValueError(f"dataset manifest {str(p)!r} has schema_version {v!r}; this torchskin reads schema "
                         f"versions {READ_SCHEMAS[0]} to {READ_SCHEMAS[-1]} ({why})")
    return man


def dataset_surface(data_dir: StrPath) -> str:
    """The skin surface model a dataset was rendered with (its config's ``skin.surface``; datasets written
    before the option existed used the subsurface-only form, "conserving"). "" without a manifest."""
    man = manifest(data_dir)
    if man is None:
        return ""
    return man.get("config", {}).get("skin", {}).get("surface", "conserving")


def dataset_bands(data_dir: StrPath) -> BandSet:
    """The bands a dataset was rendered in: its manifest's ``bands`` (``BandSet.to_json``'s list), the index bands
    (``bands.INDEX_BANDS``) for a dataset whose manifest does not record them (written before ``generate --bands``)
    or without a manifest. A one-line ``ValueError`` naming the manifest for a malformed entry."""
    man = manifest(data_dir)
    if not man or "bands" not in man:
        return INDEX_BANDS
    try:
        return BandSet.from_json(man["bands"])
    except ValueError as e:
        raise ValueError(f"dataset manifest {str(Path(data_dir) / MANIFEST)!r}: bands: {e}") from None


def describe_bands(bands: BandSet, most: int = 8) -> str:
    """The band centres for a message: all of them up to ``most``, else their count and range.

    >>> describe_bands(BandSet.parse("544,633")), describe_bands(BandSet.parse("450:1650:10"))
    ('544, 633 nm', '121 bands, 450 to 1650 nm')
    """
    if len(bands) <= most:
        return f"{', '.join(bands.labels)} nm"
    return f"{len(bands)} bands, {bands.labels[0]} to {bands.labels[-1]} nm"


def require_bands(data_dir: StrPath, needed_nm: Sequence[float], who: str) -> BandSet:
    """The dataset's bands (``dataset_bands``), checked to hold every band of ``needed_nm`` (within
    ``bands.BAND_MATCH_NM``): a one-line ``ValueError`` naming the dataset, ``who`` needs them, the missing bands
    and the bands it has otherwise. The one check of a detector kind's ``required_bands`` (``registry.train``,
    ``torchskin evaluate``)."""
    bands = dataset_bands(data_dir)
    missing = [f"{w:g}" for w in needed_nm if not has_band(bands, w)]
    if missing:
        raise ValueError(f"dataset {str(data_dir)!r} lacks the {', '.join(missing)} nm band{'s' * (len(missing) > 1)} "
                         f"that {who} needs (its bands: {describe_bands(bands)}); generate it with --bands that "
                         "include them")
    return bands


def manifest_sha256(data_dir: StrPath) -> str:
    """SHA-256 of the dataset's manifest ("" without one): names the exact data a model was trained on."""
    p = Path(data_dir) / MANIFEST
    return sha256_file(p) if p.is_file() else ""


def open_dataset(data_dir: StrPath, columns: Sequence[str] = ()) -> ds.Dataset:
    """The pyarrow dataset of the Parquet shards in ``data_dir``, checked to hold ``columns``.

    Args:
        data_dir: the dataset folder (``torchskin generate`` writes one).
        columns: the columns the caller will read.

    Returns:
        The ``pyarrow.dataset.Dataset``; a one-line ``ValueError`` for a missing folder, a folder without shards,
        a manifest of a schema this torchskin does not read (``manifest``) or missing columns.
    """
    import pyarrow.dataset as ds

    folder = Path(data_dir)
    if folder.exists() and not folder.is_dir():
        raise ValueError(f"dataset {str(folder)!r} is a file; a dataset folder is expected (torchskin generate writes one)")
    if not folder.is_dir():
        raise ValueError(f"dataset folder {str(folder)!r} does not exist (torchskin generate writes one)")
    if not any(folder.glob("*.parquet")):
        raise ValueError(f"{str(folder)!r} holds no Parquet shards: not a torchskin dataset (torchskin generate)")
    manifest(folder)  # a manifest of a schema this torchskin does not read is refused here
    try:
        d = ds.dataset(str(folder), format="parquet", exclude_invalid_files=True)
    except Exception as e:  # pyarrow raises its own types
        raise ValueError(f"cannot read the dataset in {str(folder)!r}: {str(e).splitlines()[0]}") from None
    missing = [c for c in columns if c not in d.schema.names]
    if missing:
        raise ValueError(f"dataset {str(folder)!r} lacks column(s) {missing}: not a torchskin dataset, or an older "
                         "schema (regenerate it)")
    return d


#: which frames ``read_valid`` keeps: "physical", those whose ELM reflectance is physical (``elm_valid``: what
#: evaluation and calibration use); "line", also those whose one fault is that the panels receive less light than
#: sun-facing surfaces (``elm_line_valid``: panels sunlit and the line a line, the irradiance-ratio bound aside),
#: which ``torchskin train --frames line`` (its default) learns from
FRAME_SETS = {"physical": "elm_valid", "line": "elm_line_valid"}


def read_valid(data_dir: StrPath, columns: Sequence[str], frames: str = "physical") -> tuple[pa.Table, int]:
    """The rows training and evaluation use: those of frames whose empirical line is physical.

    Args:
        data_dir: the dataset folder.
        columns: the columns to read.
        frames: "physical" (rows with ``elm_valid`` true) or "line" (rows with ``elm_line_valid`` true, which adds
            the frames whose panels are lit less than the scene's sun-facing surfaces; ``FRAME_SETS``).

    Returns:
        A pyarrow table of ``columns`` keeping only those rows (datasets without the column: ``elm_valid`` for
        "line" when ``elm_line_valid`` is missing; every row without either), and the number of rows left out.
    """
    import numpy as np

    if frames not in FRAME_SETS:
        raise ValueError(f"frames must be one of {', '.join(FRAME_SETS)}, got {frames!r}")
    d = open_dataset(data_dir, columns)
    flag = FRAME_SETS[frames]
    if flag not in d.schema.names:
        flag = "elm_valid"
    if flag not in d.schema.names:
        return d.to_table(columns=list(columns)), 0
    t = d.to_table(columns=list(dict.fromkeys([*columns, flag])))
    valid = t.column(flag)
    excluded = len(t) - int(np.count_nonzero(valid.to_numpy(zero_copy_only=False)))
    return t.filter(valid).select(list(columns)), excluded


def read_rows(data_dir: StrPath, columns: Sequence[str], frames: str = "physical",
              optional: Sequence[str] = ()) -> Rows:
    """The rows training and evaluation use (``read_valid``: the frames ``frames`` names), as numpy columns.

    Args:
        data_dir: the dataset folder.
        columns: the columns to read (``dataset.schema.COLUMNS``); a missing one is a one-line ``ValueError``
            (``open_dataset``).
        frames: "physical" or "line" (``FRAME_SETS``).
        optional: more columns, read when the dataset has them (older schemas lack some).

    Returns:
        ``dataset.schema.Rows``: each column a writable numpy array (strings as objects), the number of rows
        left out (``Rows.excluded``) and the dataset's bands (``Rows.band_set``: ``dataset_bands``, whose
        ``BandSet.columns`` are its reflectance columns); ``Rows.nd`` gives the normalized difference of any band
        pair.
    """
    names = list(dict.fromkeys(columns))
    if optional:
        present = set(open_dataset(data_dir, names).schema.names)
        names += [c for c in dict.fromkeys(optional) if c in present and c not in names]
    t, excluded = read_valid(data_dir, names, frames)
    out = {}
    for c in names:
        a = t.column(c).to_numpy(zero_copy_only=False)
        out[c] = a if a.flags.writeable else a.copy()
    return Rows(out, excluded, dataset_bands(data_dir))


__all__ = ["FRAME_SETS", "IMAGES_DIR", "MANIFEST", "READ_SCHEMAS", "RENDER_REVISION", "SCHEMA_VERSION",
           "dataset_bands", "dataset_files", "dataset_surface", "describe_bands", "intact", "manifest",
           "manifest_sha256", "open_dataset", "read_rows", "read_valid", "require_bands", "sha256_file", "shard_name"]
