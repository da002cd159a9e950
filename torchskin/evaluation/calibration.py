"""Held-out calibration of a checkpoint to the false-alarm budgets: one scalar per model (the box scale or the
classifier's threshold), recorded in the calibrated checkpoint's metadata."""

from __future__ import annotations

import math
import os

import torch

from ..detectors import registry
from ..detectors.protocol import CalibrationData
from .candidates import load_model
from .metrics import MIN_REFLECTANCE, HeldOut, held_out
from .regions import earthlib_test


def calibration_data(rows: HeldOut, test_R: torch.Tensor, test_pts: torch.Tensor,
                     min_reflectance: float = MIN_REFLECTANCE) -> CalibrationData:
    """What a kind calibrates itself on (``CalibrationData``): the held-out ``rows`` and the earthlib test spectra
    ``test_R`` with their index points ``test_pts`` (``regions.earthlib_test``), each judged above the brightness
    floor only (the others' points NaN)."""
    tb = test_R.mean(-1) > min_reflectance
    return CalibrationData(R=rows.R, X=rows.X, ndgri=rows.g, ndsi=rows.s, ndvn=rows.v, cfg_X=rows.cfg_X,
                           nonskin=~rows.label, bright=rows.R.mean(-1) > min_reflectance, test_R=test_R,
                           test_bright=tb, test_pts=torch.where(tb[:, None], test_pts,
                                                                torch.full_like(test_pts, math.nan)))


def calibrate_to_budget(model_path: str | os.PathLike, data_dir: str | os.PathLike, out_path: str | os.PathLike,
                        scene_budget: float = 1e-4, pfa_budget: float = 1e-3,
                        min_reflectance: float = MIN_REFLECTANCE, iters: int = 30) -> dict:
    """Calibrate a checkpoint to the false-alarm budgets on a validation dataset (the held-out set): one scalar,
    the largest box scale (box models: ``BoxModel.scale``, every box shrunk about its centre) or the lowest
    logit threshold (classifiers), at which the share of the dataset's non-skin pixels called skin (under the
    brightness floor, as ``evaluate`` judges it) is within ``scene_budget`` and the earthlib test spectra within
    ``pfa_budget`` in every configuration of the dataset; never looser than the checkpoint's own tuning. Writes
    the calibrated checkpoint to ``out_path`` (its metadata records the calibration) and returns the record.

    Training holds the scene budget on the training dataset's own pixels; this holds it on pixels of other
    confusers and clothing (the test partition), where configuration-dependent boxes, shaped around what
    training showed them, let more through. The comparison and the choice then happen at the same budgets,
    and the fresh test set stays untouched."""
    if not (0.0 <= scene_budget < 1.0) or not (0.0 <= pfa_budget < 1.0):
        raise ValueError(f"budgets must lie in [0, 1), got scene {scene_budget}, earthlib {pfa_budget}")
    model, ck = load_model(model_path)
    calibrate = getattr(model, "calibrate_to_budget", None)
    if calibrate is None:
        raise ValueError(f"{str(model_path)!r}: detector kind {registry.kind_of(model)!r} cannot be calibrated")
    from ..dataset.files import require_bands
    from ..export import model_bands

    bands = model_bands(model).centers  # the model's own bands: the index bands for box kinds
    require_bands(data_dir, bands, f"--model {model_path}")
    rows = held_out(data_dir, list(model.features), bands)
    c = calibrate(calibration_data(rows, *earthlib_test(bands), min_reflectance), scene_budget, pfa_budget, iters)
    knob, start, value, rate = c["knob"], c["before"], c["after"], c["pfa_scene"]
    record = {"data": str(data_dir), "scene_budget": scene_budget, "pfa_budget": pfa_budget, "knob": knob,
              "before": start, "after": value, "pfa_scene": rate, "rows": rows.n}
    registry.save(model, out_path, {**ck.get("meta", {}), "calibration": record})
    return record


__all__ = ["calibrate_to_budget", "calibration_data"]
