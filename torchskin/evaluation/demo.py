"""The render demo: the shipped detector on the thesis geometry, end to end (render, onboard ELM, onboard
runtime), against the static box (``thesis_frame``)."""

from __future__ import annotations

import os

import numpy as np
import torch


def thesis_frame(detector_path: str | os.PathLike, size: int = 160, sun_zenith_deg: float = 45.0,
                 sun_azimuth_deg: float = 20.0, min_reflectance: float = 0.005,
                 plot: str | os.PathLike | None = None) -> dict:
    """The shipped detector on the thesis geometry, end to end: ``render``'s default scene (horizontal camera at
    9.449 m, Type I/II subject between a 0.97 and a 0.03 panel, sensor noise on) at ``size`` x ``size`` under
    the given sun, its signal frame calibrated by the onboard ELM through the panels' pixel regions, then
    ``detector.onnx`` through the onboard runtime (negative noise clipped, brightness floor). Returns the
    sunlit-skin detection of the learned boundaries and of the static box, the learned false alarms and the
    largest difference between the onboard and the renderer's ELM reflectance. ``plot``: a PNG of the 1080 nm
    reflectance beside both masks."""
    from ..angles import relative_azimuth_deg
    from ..detectors.features import DIFFUSE_SHARE, diffuse_share
    from ..onboard import OnboardDetector, elm_apply, elm_fit
    from ..render.elm import panel_regions
    from ..render.materials import compile_materials
    from ..render.pipeline import render
    from ..render.scene import Camera, Sun, default_scene
    from ..render.sensor import Sensor

    sc = default_scene(camera=Camera(width=size, height=size),
                       sun=Sun(zenith_deg=sun_zenith_deg, azimuth_deg=sun_azimuth_deg, sky_fraction=0.1))
    res = render(sc, sensor=Sensor())
    signal = res.signal[0, 0].permute(2, 0, 1).cpu().numpy()
    regions = panel_regions(res.panel_pixels, list(sc.panels), size, size)
    reference = compile_materials(sc.materials, sc.bands, sc.suns, dtype=torch.float64).reference  # (M, B) DHR
    refs = {p: reference[list(sc.materials).index(sc.mesh(p).material)].tolist() for p in sc.panels}
    fit = elm_fit(signal, [(regions[p], refs[p]) for p in sc.panels])
    cube = elm_apply(signal, fit["gain"], fit["offset"])[None]
    rel = relative_azimuth_deg(sun_azimuth_deg, sc.cameras[0].azimuth_deg)
    det = OnboardDetector(detector_path)
    # the frame's configuration in the detector's features: the angles, and the sky's diffuse share of the light on
    # a horizontal surface (the scene's sky gives sky_fraction times the sun's normal irradiance there)
    row = det.config_row(sun_zenith_deg=sun_zenith_deg, camera_zenith_deg=sc.cameras[0].zenith_deg,
                         relative_azimuth_deg=rel, **{DIFFUSE_SHARE: float(diffuse_share(sc.suns[0].sky_fraction,
                                                                                         sun_zenith_deg))})
    out = det(cube, [row], negative="clip", min_reflectance=min_reflectance)
    skin, lit = res.skin[0].cpu().numpy(), res.lit[0, 0].cpu().numpy()
    sunlit = skin & lit
    learned, static = out["mask"][0], res.mask[0, 0].cpu().numpy()
    n = max(int(sunlit.sum()), 1)
    if plot is not None:
        from .figures import thesis_frame_plot

        thesis_frame_plot(plot, cube[0, 2], static, learned, skin, sunlit, sun_zenith_deg)
    return {"sunlit_skin_pixels": int(sunlit.sum()), "pd_sunlit_learned": float((learned & sunlit).sum() / n),
            "pd_sunlit_static": float((static & sunlit).sum() / n), "false_alarms_learned": int((learned & ~skin).sum()),
            "out_of_domain": bool(out["out_of_domain"].any()),
            "elm_max_diff": float(np.abs(cube[0] - res.reflectance[0, 0].permute(2, 0, 1).cpu().numpy()).max())}


__all__ = ["thesis_frame"]
