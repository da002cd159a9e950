"""Dataset folder files, without the renderer's imports: the manifest's name, checksums, and reading the rows
of frames whose ELM is valid (what training and evaluation use)."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

MANIFEST = "_manifest.json"  # leading underscore: Parquet readers skip it when reading the folder


def sha256_file(path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def manifest(data_dir) -> dict | None:
    """The dataset's manifest, or None when the folder has none."""
    p = Path(data_dir) / MANIFEST
    return json.loads(p.read_text()) if p.is_file() else None


def dataset_surface(data_dir) -> str:
    """The skin surface model a dataset was rendered with (its config's ``skin.surface``; datasets written
    before the option existed used the subsurface-only form, "conserving"). "" without a manifest."""
    man = manifest(data_dir)
    if man is None:
        return ""
    return man.get("config", {}).get("skin", {}).get("surface", "conserving")


def manifest_sha256(data_dir) -> str:
    """SHA-256 of the dataset's manifest ("" without one): names the exact data a model was trained on."""
    p = Path(data_dir) / MANIFEST
    return sha256_file(p) if p.is_file() else ""


def read_valid(data_dir, columns):
    """A pyarrow table of ``columns`` from the Parquet shards in ``data_dir``, keeping only frames whose
    reference panels were sunlit (``elm_valid``; datasets without the column keep every row), and the number
    of rows left out."""
    import numpy as np
    import pyarrow.dataset as ds

    d = ds.dataset(str(data_dir), format="parquet")
    if "elm_valid" not in d.schema.names:
        return d.to_table(columns=list(columns)), 0
    t = d.to_table(columns=list(dict.fromkeys([*columns, "elm_valid"])))
    valid = t.column("elm_valid")
    excluded = len(t) - int(np.count_nonzero(valid.to_numpy(zero_copy_only=False)))
    return t.filter(valid).select(list(columns)), excluded


__all__ = ["MANIFEST", "dataset_surface", "manifest", "manifest_sha256", "read_valid", "sha256_file"]
