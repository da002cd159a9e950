"""Onboard runtime: load the exported ONNX models and run them with numpy and onnxruntime only (no torch).

    det = OnboardDetector("exports/detector.onnx")
    row = det.config_row(sun_zenith_deg=45, camera_zenith_deg=90, relative_azimuth_deg=20, diffuse_share=0.17)
    out = det(cube, [row])       # cube (B, 4, H, W) float32 reflectance, config (B, k) in det.features
    out["mask"], out["score"], out["out_of_domain"]

``score`` is 1 inside the region and 0 outside for the shipped lookup table; for a box detector, the smallest
margin to a box edge in index units weighted by the band-pair sum (positive inside; see
``torchskin.detectors.boxes.BoxDetector``).

Inputs are validated: wrong rank, band count or dtype, NaN or negative reflectance, and values far outside
[0, 1.2] (below ``REFLECTANCE_MIN``, above ``REFLECTANCE_MAX`` in more than ``REFLECTANCE_MAX_SHARE`` of the
values: digital numbers, per cent; a glint is allowed; or any value above ``REFLECTANCE_CEILING``, which no camera
records) raise ``ValueError``;
float64, float16 and big-endian cubes are converted to float32 (``io.as_float32``);
configurations outside the training domain are flagged per frame in ``out_of_domain`` (never silently used).
Calibrated frames of dark pixels (sky, deep shadow) carry slightly negative reflectance from sensor noise:
``det(cube, config, negative="clip")`` sets those values to 0 instead and counts them per frame in
``clipped_values`` (a pixel whose band pairs sum to 0 is never skin).

The ELM of camera frames (``panel_signal``, ``elm_fit``, ``elm_apply``) is numpy too; the command line

The package's modules: ``runtime`` (``OnboardDetector``, ``OnboardBoxes``), ``heads`` (the heads a detector graph
runs on: ``detector_head``), ``checks`` (the reflectance range), ``bandplan`` (the model's bands from a cube),
``elm`` (the empirical line) and ``stream`` (cube files: ``load_cube``, ``detect_file``, ``calibrate_file``, masks).
"""

from __future__ import annotations

from .bandplan import MAX_SAMPLE_GAP_NM, apply_plan, band_plan, match_bands, model_fwhm, plan_bands
from .checks import (
    REFLECTANCE_CEILING,
    REFLECTANCE_MAX,
    REFLECTANCE_MAX_SHARE,
    REFLECTANCE_MIN,
    check_reflectance_range,
)
from .elm import check_panel_regions, elm_apply, elm_fit, elm_line, panel_reference, panel_signal
from .heads import BOX_HEAD_KINDS, FLOOR_BAND, detector_head
from .runtime import SHIPPED_DETECTOR, OnboardBoxes, OnboardDetector, model_inputs
from .stream import TILE_BYTES, calibrate_file, detect_file, load_cube, mask_rows, write_mask

__all__ = [
    "BOX_HEAD_KINDS", "FLOOR_BAND", "MAX_SAMPLE_GAP_NM", "REFLECTANCE_CEILING", "REFLECTANCE_MAX",
    "REFLECTANCE_MAX_SHARE", "REFLECTANCE_MIN", "SHIPPED_DETECTOR", "TILE_BYTES", "OnboardBoxes", "OnboardDetector",
    "apply_plan", "band_plan", "calibrate_file", "check_panel_regions", "check_reflectance_range", "detect_file",
    "detector_head", "elm_apply", "elm_fit", "elm_line", "load_cube", "mask_rows", "match_bands", "model_fwhm", "plan_bands",
    "model_inputs", "panel_reference", "panel_signal", "write_mask",
]
