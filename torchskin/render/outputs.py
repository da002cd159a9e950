"""Stage 7 of the renderer: what a frame reports and writes. The frame's summary (skin pixels, the detected
fraction, whether its ELM is physical), connected components of the detection mask, and the files: band PNGs,
the reflectance and signal cubes, the mask PNGs and ``render.json``.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..detect import has_index_bands
from ..io import bands_sidecar_text, save_npy, sidecar_path, write_text
from .elm import (
    ELM_MAX_IRRADIANCE_RATIO,
    ELM_MIN_SUNLIT,
    elm_line_valid,
    panel_irradiance_ratio,
    panel_median_noise_dn,
    panel_normals,
    panel_regions,
    panel_sunlit_fraction,
)
from .light import uses_atmosphere
from .pipeline import RenderResult
from .scene import DEFAULT_ILLUMINATION, Scene
from .sensor import Sensor


def detections(mask: np.ndarray, truth: np.ndarray | None = None, min_area: int = 4) -> list[dict]:
    """Connected components of a 2-D mask (scikit-image): bounding box, area, centroid, and the fraction
    of the component on the truth mask when given."""
    from skimage.measure import label, regionprops

    lab = label(mask, connectivity=2)
    out = []
    for r in regionprops(lab):
        if r.area < min_area:
            continue
        d = {"bbox": [int(x) for x in r.bbox], "area": int(r.area),
             "centroid": [float(r.centroid[0]), float(r.centroid[1])]}
        if truth is not None:
            d["on_subject"] = float(truth[lab == r.label].mean())
        out.append(d)
    return sorted(out, key=lambda d: -d["area"])


def line_valid(result: RenderResult, s: int = 0, c: int = 0, sensor: Sensor | None = None) -> bool:
    """Whether the empirical line of frame (sun ``s``, camera ``c``) is a line (``elm.elm_line_valid``): its
    panels ``ELM_MIN_SEPARATION_SIGMA`` σ of their medians' noise apart in every band (``sensor``'s noise model;
    without a sensor, or without noise, the ADC's or none) and a finite positive gain. True for a frame without
    two panels."""
    import torch

    names = list(result.panels)
    if len(names) < 2:
        return True
    pv = torch.tensor([result.panels[p]["signal"][s][c] for p in names[:2]], dtype=torch.float64)
    refs = torch.tensor([result.panels[p]["reference"][s][c] for p in names[:2]], dtype=torch.float64)
    if sensor is None:
        noise = torch.zeros_like(pv)
    else:
        n = torch.tensor([[float(len(result.panel_pixels[k][c]))] for k in range(2)], dtype=torch.float64)
        noise = panel_median_noise_dn(pv, n, sensor.read_noise_e, 2.0 ** int(sensor.adc_bits) / sensor.full_well_e,
                                      sensor.quantize, sensor.noise)
    return bool(elm_line_valid(pv, refs, noise))


def irradiance_ratio(result: RenderResult, sun_dir: Sequence[float], s: int = 0, c: int = 0) -> float:
    """``elm.panel_irradiance_ratio`` of frame (sun ``s``, camera ``c``), the sun towards ``sun_dir`` (unit, z up):
    how many times its reflectance a sunlit surface can read through the frame's empirical line (1.0 for a frame
    without reference panels)."""
    import torch

    if len(result.panels) < 2:
        return 1.0
    light = result.light
    d = torch.tensor([list(sun_dir)], dtype=torch.float64)
    normals = panel_normals(result.gbuffer, result.panel_pixels[:2], c).double().cpu()
    return float(panel_irradiance_ratio(light.beam[s:s + 1].double().cpu(), light.sky[s:s + 1].double().cpu(), d,
                                        normals)[0])


def summary(result: RenderResult, s: int = 0, c: int = 0, sensor: Sensor | None = None,
            sun_dir: Sequence[float] | None = None) -> dict:
    """Skin pixel counts and the fraction the rules detector finds, for sun ``s`` and camera ``c``; whether the
    frame's ELM is physical (``elm_valid``): every reference panel at least ``ELM_MIN_SUNLIT`` sunlit (without
    sunlit panels the empirical line is set by sky light), the line through them a line (``line_valid`` with
    ``sensor``'s noise), and, given the sun's direction ``sun_dir``, no surface able to receive more than
    ``ELM_MAX_IRRADIANCE_RATIO`` times the panels' irradiance (``irradiance_ratio``; with panels lit less than the
    scene, reflectance reads several times too high)."""
    skin = result.skin[c]
    lit = skin & result.lit[s, c]
    det = result.mask[s, c]
    n, nl = int(skin.sum()), int(lit.sum())
    sunlit = panel_sunlit_fraction(result.lit[s, c], result.panel_pixels, c)
    line = line_valid(result, s, c, sensor)
    ratio = None if sun_dir is None else irradiance_ratio(result, sun_dir, s, c)
    return {
        "skin_pixels": n,
        "sunlit_skin_pixels": nl,
        "detected_fraction": float(det[skin].float().mean()) if n else 0.0,
        "detected_fraction_sunlit": float(det[lit].float().mean()) if nl else 0.0,
        "false_alarm_pixels": int((det & ~skin).sum()),
        "rules_detector": has_index_bands(result.bands),  # false: the bands lack 544/633/1080/1580 nm
        "elm_valid": all(f >= ELM_MIN_SUNLIT for f in sunlit) and line
        and (ratio is None or ratio <= ELM_MAX_IRRADIANCE_RATIO),
        "elm_line_valid": line,
        "panel_sunlit_fraction": sunlit,
        **({} if ratio is None else {"panel_irradiance_ratio": ratio}),
    }


def elm_warning(info: dict) -> str | None:
    """Why a frame's ELM is not physical, in one sentence, from its ``summary`` (None when it is)."""
    if info["elm_valid"]:
        return None
    if min(info["panel_sunlit_fraction"], default=1.0) < ELM_MIN_SUNLIT:
        return ("the reference panels are not sunlit (sunlit share of their interiors "
                f"{', '.join(f'{v:.2f}' for v in info['panel_sunlit_fraction'])}; the sun is behind or below them, or "
                "the subject shadows them): the empirical line is set by sky light and the reflectance is not "
                "physical (elm_valid false)")
    if not info["elm_line_valid"]:
        return ("the empirical line through the reference panels is not physical: they are too close in signal for "
                "the sensor noise, or its gain is not positive (elm_valid false)")
    return (f"the reference panels receive less light than the scene: a surface facing the sun receives up to "
            f"{info['panel_irradiance_ratio']:.2f} times their irradiance (more than {ELM_MAX_IRRADIANCE_RATIO:g}; a low "
            "sun grazing the panels, or panels turned from it), so the line reads sunlit surfaces that many times "
            "their reflectance and the reflectance is not physical (elm_valid false)")


def previous_outputs(out_dir: str | Path) -> list[Path]:
    """The files an earlier ``write_outputs`` left in ``out_dir`` as its ``render.json`` lists them: the cubes and
    their sidecars (``cubes``), the band PNGs (``bands_nm``), the mask PNGs and ``render.json`` itself; those that
    exist. ``torchskin render --overwrite`` removes them before writing, so that the folder holds one render (not
    an earlier render's cubes of another ``--format`` or PNGs of other ``--bands``). [] without a readable
    ``render.json``; other files are never listed."""
    out = Path(out_dir)
    try:
        doc = json.loads((out / "render.json").read_text())
        names = ["render.json", "mask.png", "mask_annotated.png"]
        names += [f"band_{float(b[0]):g}nm.png" for b in doc.get("bands_nm", [])]
        for quantity in ("reflectance", "signal"):
            names += [str(f) for f in doc.get("cubes", {}).get(quantity, {}).get("files", [])]
    except (OSError, ValueError, TypeError, AttributeError, IndexError, KeyError):
        return []
    paths = [out / n for n in dict.fromkeys(names) if Path(n).name == n]  # plain names inside out_dir only
    return [p for p in paths if p.is_file()]


def write_outputs(result: RenderResult, scene: Scene | dict, out_dir: str | Path, s: int = 0, c: int = 0,
                  sensor: Sensor | None = None, fmt: str = "npy", sky_view: str | None = None) -> dict:
    """Band PNGs (false-colour reflectance), the reflectance cube (bands x H x W, ``reflectance.npy``), the
    sensor signal cube before ELM (``signal.npy``, digital numbers), each with its wavelengths in a sidecar
    (``reflectance.bands.json``, ``signal.bands.json``: ``io.bands_sidecar_text``), the rules detector's mask, ``mask.png``: an
    RGB PNG of exactly the frame's H x W pixels (one per frame pixel, no axes or title; ``plots.mask_png``),
    detected skin green (26, 217, 51), missed skin red (230, 38, 26), false alarms yellow (255, 230, 26),
    everything else black; the same mask as an annotated figure with a colour key, ``mask_annotated.png``; and
    ``render.json`` (``scene``: the ``Scene`` or its ``to_dict()``, each sun's ``atmosphere`` null under a light
    model that reads none, ``light.uses_atmosphere``; timing, panels with their pixel regions, detections) in
    ``out_dir``, for sun ``s`` and camera ``c``; ``sensor``: the one rendered with (its noise
    model judges the empirical line, ``summary``); ``sky_view``: the render's sky-view method, recorded as
    ``sky_view`` when given. ``fmt``: the cubes' format, "npy" (the default, above), "envi"
    (``reflectance.hdr`` over ``reflectance.img``, ``signal.hdr`` over ``signal.img``) or "tiff"
    (``reflectance.tif``, ``signal.tif``), each with its wavelengths, FWHM and units in the header
    (``cubefiles.CubeWriter``); ``render.json``'s ``cubes`` lists the files and their format. Returns the
    summary."""
    if isinstance(scene, Scene):
        suns = scene.suns
        scene = scene.to_dict()
    elif isinstance(scene, dict):
        suns = Scene.from_dict(scene).suns
    if not isinstance(scene, dict):
        raise TypeError(f"scene must be a Scene or its to_dict(), got {type(scene).__name__}")  # before any file
    if not uses_atmosphere(scene.get("illumination", DEFAULT_ILLUMINATION)):  # record what the light used
        scene = {**scene, "suns": [{**sun, "atmosphere": None} for sun in scene["suns"]]}
    from ..cubefiles import QUANTITY_UNITS, WRITE_FORMATS, write_cube
    from ..plots import band_images, mask_image, mask_png

    if fmt not in WRITE_FORMATS:
        raise ValueError(f"fmt must be one of {', '.join(WRITE_FORMATS)}, got {fmt!r}")  # before any file
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    centres = [float(b.center_nm) for b in result.bands]  # the cubes' wavelengths, for detect and calibrate
    fwhm = [float(b.fwhm_nm) for b in result.bands]  # 0: monochromatic
    cubes: dict[str, Any] = {"format": fmt}
    for quantity in ("reflectance", "signal"):
        cube = result.cube(s, c, quantity)
        if fmt == "npy":
            save_npy(out / f"{quantity}.npy", cube)
            write_text(sidecar_path(out / f"{quantity}.npy"), bands_sidecar_text(centres, fwhm, quantity))
            files = [f"{quantity}.npy", sidecar_path(out / f"{quantity}.npy").name]
        else:
            path = write_cube(out / f"{quantity}.{'hdr' if fmt == 'envi' else 'tif'}", cube, fmt, centres, fwhm,
                              quantity)
            files = [path.name, f"{quantity}.img"] if fmt == "envi" else [path.name]
        cubes[quantity] = {"files": files, "units": QUANTITY_UNITS[quantity]}
    band_images([out / f"band_{b.label}nm.png" for b in result.bands],
                [result.reflectance[s, c, :, :, k] for k in range(len(result.bands))],
                [f"{b.center_nm:g} nm reflectance (ELM)" for b in result.bands])
    mask_png(out / "mask.png", result.mask[s, c], result.skin[c])
    mask_image(out / "mask_annotated.png", result.mask[s, c], result.skin[c],
               f"rules detector mask ({result.mask.shape[-1]} x {result.mask.shape[-2]} px)")
    info = summary(result, s, c, sensor, sun_dir=[float(x) for x in suns[s].direction] if s < len(suns) else None)
    dets = detections(result.mask[s, c].cpu().numpy(), result.skin[c].cpu().numpy())
    H, W = result.mask.shape[-2:]
    regions = panel_regions(result.panel_pixels, list(result.panels), H, W, camera=c)
    panels = {p: {**v, "region": regions[p]} for p, v in result.panels.items()}
    doc = {"summary": info, "timing_s": result.timing, "panels": panels, "detections": dets,
           "scene": scene, "bands_nm": [[b.center_nm, b.fwhm_nm] for b in result.bands],
           "illumination": result.light.summary(result.bands), "cubes": cubes}
    if sky_view is not None:
        doc["sky_view"] = sky_view
    write_text(out / "render.json", json.dumps(doc, indent=1))
    return info
