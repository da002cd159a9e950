"""The ``boxes`` kind's training rows from a generated dataset: configuration features and (NDGRI, NDSI, NDVN)
of its skin pixels (``load_skin_rows``) and of its non-skin pixels (``load_scene_rows``)."""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np
import torch

from ..features import BAND_COLUMNS, FEATURES, MIN_REFLECTANCE


def load_skin_rows(data_dir: str | os.PathLike, features: Sequence[str] = FEATURES,
                   sunlit_only: bool = False, frames: str = "physical") -> tuple[torch.Tensor, torch.Tensor]:
    """Features (n, k) and (NDGRI, NDSI, NDVN) (n, 3) of the skin pixels of a generated dataset (float32),
    sunlit and shadowed (``sunlit_only``: sunlit only), from the frames ``frames`` names
    (``dataset.files.read_rows``: "physical", ``elm_valid``; "line", ``elm_line_valid``)."""
    X, Y = _index_rows(data_dir, features, skin=True, sunlit_only=sunlit_only, frames=frames)
    if len(X) == 0:
        raise ValueError(f"no usable {'sunlit ' if sunlit_only else ''}skin pixels in {str(data_dir)!r}")
    return X, Y


def load_scene_rows(data_dir: str | os.PathLike, features: Sequence[str] = FEATURES,
                    min_reflectance: float = MIN_REFLECTANCE, frames: str = "physical"
                    ) -> tuple[torch.Tensor, torch.Tensor]:
    """Features (n, k) and (NDGRI, NDSI, NDVN) (n, 3) of the non-skin pixels of a generated dataset (clothing,
    ground and confuser patches, in sun and in shadow, as the camera saw them; the frames ``frames`` names, as
    ``load_skin_rows``; float32): the
    scene false alarms ``learn`` holds to its scene budget. Pixels whose mean reflectance is not above
    ``min_reflectance`` (the detector's brightness floor: never skin) keep their row with NaN indices, which no
    box holds: they count in the budget's denominator, as in the evaluation, and constrain nothing."""
    return _index_rows(data_dir, features, skin=False, sunlit_only=False, floor=min_reflectance, frames=frames)


def _index_rows(data_dir: str | os.PathLike, features: Sequence[str], skin: bool,
                sunlit_only: bool, floor: float | None = None, frames: str = "physical"
                ) -> tuple[torch.Tensor, torch.Tensor]:
    from ...dataset.files import read_rows

    rows = read_rows(data_dir, [*features, "ndgri", "ndsi", "label", "shadow", *BAND_COLUMNS], frames)
    keep = rows["label"].copy() if skin else ~rows["label"]
    if sunlit_only:
        keep &= ~rows["shadow"]
    X = rows.stack(features)[keep]
    R = rows.bands(np.float64)[keep]
    v = rows.index("ndvn", np.float64)[keep]  # NDVN in float64 (NaN where the band sum is 0)
    Y = np.stack([rows["ndgri"][keep], rows["ndsi"][keep], v], -1)
    ok = np.isfinite(X).all(1) & np.isfinite(Y).all(1)
    if floor is not None:  # below the brightness floor: never a detection (NaN indices), still a row
        Y[~(R.mean(1) > floor)] = np.nan
        ok = np.isfinite(X).all(1)
    return torch.from_numpy(X[ok].astype(np.float32)), torch.from_numpy(Y[ok].astype(np.float32))


__all__ = ["load_scene_rows", "load_skin_rows"]
