"""The dataset schema (``torchskin.dataset.schema``) and its row reader (``dataset.files.read_rows``): the band
columns follow the index bands, the normalized differences computed on rows are the detectors' own bits, and the
reader keeps ``read_valid``'s frames and checks."""

import json

import numpy as np
import pytest
import torch

from torchskin.bands import INDEX_BANDS_NM
from torchskin.dataset.files import MANIFEST, read_rows
from torchskin.dataset.schema import BAND_COLUMNS, COLUMNS, FIXED_COLUMNS, INDICES, STORED_INDICES, Rows
from torchskin.detect import ratio_indices


def test_the_columns_follow_the_index_bands():
    assert BAND_COLUMNS == ("r544", "r633", "r1080", "r1580") and len(BAND_COLUMNS) == len(INDEX_BANDS_NM)
    assert list(COLUMNS) == [*FIXED_COLUMNS, *BAND_COLUMNS, *STORED_INDICES]  # the shards' column order
    assert COLUMNS["r1080"] == ("float32", "ELM reflectance at 1080 nm", "")
    assert COLUMNS["ndgri"] == ("float32", "(r544 - r633) / (r544 + r633)", "")
    assert COLUMNS["ndsi"] == ("float32", "(r1080 - r1580) / (r1080 + r1580)", "")
    assert set(STORED_INDICES) < set(INDICES) and "ndvn" not in COLUMNS


def _rows(R: np.ndarray) -> Rows:
    return Rows({c: R[:, k].copy() for k, c in enumerate(BAND_COLUMNS)})


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_row_indices_are_the_detectors_bits(dtype):
    """``Rows.index`` (numpy) gives bit for bit what ``detect.ratio_indices`` (torch) gives on the same float32
    columns cast to ``dtype`` (the boxes' training rows: float64; the evaluation: float32), zero sums included."""
    rng = np.random.default_rng(0)
    R = rng.uniform(0.0, 1.0, (4000, 4)).astype(np.float32)
    R[:50, :2] = 0.0  # undefined NDGRI and part-defined NDVN
    R[50:100] = 0.0  # every index undefined
    R[100:150, 2] = -R[100:150, 3]  # NDSI sum exactly 0
    rows = _rows(R)
    want = ratio_indices(torch.from_numpy(R.astype(dtype)))
    for name, w in zip(("ndgri", "ndsi", "ndvn"), want):
        got = rows.index(name, dtype)
        assert got.dtype == dtype
        np.testing.assert_array_equal(got.view(np.uint8), w.numpy().view(np.uint8), err_msg=name)
    assert np.isnan(rows.index("ndvn", dtype)[50:100]).all()
    np.testing.assert_array_equal(rows.nd((544, 633), (1080, 1580), dtype), rows.index("ndvn", dtype))
    np.testing.assert_array_equal(rows.bands(dtype), R.astype(dtype))


def _dataset(tmp_path, with_line=True):
    import pyarrow as pa
    import pyarrow.parquet as pq

    n = 6
    cols = {c: pa.array(np.arange(n, dtype=np.float32) / 10 + k) for k, c in enumerate(BAND_COLUMNS)}
    cols["label"] = pa.array([True, False] * 3)
    cols["elm_valid"] = pa.array([True, True, False, False, True, False])
    if with_line:
        cols["elm_line_valid"] = pa.array([True, True, True, False, True, False])
    cols["material"] = pa.array(["skin", "ground"] * 3)
    pq.write_table(pa.table(cols), tmp_path / "shard-00000.parquet")
    (tmp_path / MANIFEST).write_text(json.dumps({"schema_version": 6}))
    return tmp_path


def test_read_rows_keeps_the_frames_and_checks(tmp_path):
    d = _dataset(tmp_path)
    rows = read_rows(d, ["label", *BAND_COLUMNS])
    assert len(rows) == 3 and rows.excluded == 3 and list(rows.columns) == ["label", *BAND_COLUMNS]
    assert rows["label"].tolist() == [True, False, True] and rows["r544"].flags.writeable
    line = read_rows(d, ["label"], frames="line", optional=["material", "confuser"])
    assert len(line) == 4 and line.excluded == 2 and list(line.columns) == ["label", "material"]
    assert line["material"].tolist() == ["skin", "ground", "skin", "skin"]  # rows 0, 1, 2 and 4
    with pytest.raises(ValueError, match=r"lacks column\(s\) \['ndsi'\]"):
        read_rows(d, ["label", "ndsi"])
    with pytest.raises(ValueError, match="frames must be one of"):
        read_rows(d, ["label"], frames="all")
    (d / MANIFEST).write_text(json.dumps({"schema_version": 99}))
    with pytest.raises(ValueError, match="schema_version 99"):
        read_rows(d, ["label"])
