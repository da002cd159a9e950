"""The renderer as named stages, each a module with typed inputs and outputs (read them in this order):

==============  ==========================================================================================
``scene``       the scene as plain data (materials, meshes, cameras, suns, bands; JSON round trip; no torch)
``meshes``      mesh descriptions -> triangles (primitives, anny bodies, OBJ/PLY files)
``raycast``     camera and shadow rays -> ``GBuffer`` (open3d ``RaycastingScene``): ``rasterize(scene)``
``materials``   a registry of material kinds -> per-band tables and BRDFs: ``compile_materials``
``light``       the suns' spectra
``shade``       G-buffer + material tables + suns -> radiance: ``shade``
``sensor``      radiance -> digital numbers (eq 2.5.2): ``Sensor``, ``sensor_signal``
``elm``         digital numbers + reference-panel pixels -> reflectance (eqs 2.5.4-2.5.7, 3.3.1-3.3.3)
``pipeline``    the stages in order: ``render`` (frames), ``render_pixels`` (chosen pixels; datasets)
``outputs``     the frame's summary and files: ``summary``, ``write_outputs``
==============  ==========================================================================================

The names below load their module on first use, so ``import torchskin.render.scene`` imports no torch.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "render": "pipeline", "render_pixels": "pipeline", "RenderResult": "pipeline",
    "Sensor": "sensor", "sensor_signal": "sensor",
    "Scene": "scene", "Material": "scene", "MeshSpec": "scene", "Camera": "scene", "Sun": "scene",
    "default_scene": "scene", "panel_materials": "scene",
    "GBuffer": "raycast", "Raycaster": "raycast", "rasterize": "raycast",
    "MaterialCache": "materials", "MaterialKind": "materials", "compile_materials": "materials",
    "register": "materials",
    "shade": "shade",
    "summary": "outputs", "write_outputs": "outputs",
}
_STAGES = ("scene", "meshes", "raycast", "materials", "light", "shade", "sensor", "elm", "pipeline", "outputs")


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        return getattr(importlib.import_module(f".{_EXPORTS[name]}", __name__), name)
    if name in _STAGES:
        return importlib.import_module(f".{name}", __name__)
    raise AttributeError(f"module 'torchskin.render' has no attribute {name!r}")


__all__ = [*_EXPORTS, *_STAGES]
