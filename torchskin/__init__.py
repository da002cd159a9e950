"""torchskin: physics-based multispectral skin reflectance, rendering and detector adaptation in PyTorch.

Modules: ``tissue`` (9-layer Kubelka-Munk skin), ``optics`` (Fresnel, Schlick, microfacet lobe, combined
BRDF), ``detect`` (NDSI/NDGRI, rules box, Bhattacharyya), ``bands``, ``angles``, ``data``, ``render`` (the
renderer's stages: scene, meshes, raycast, materials, light, shade, sensor, elm, pipeline, outputs), ``fit``,
``dataset``, ``detectors`` (the detector kinds: ``boxes``, ``classifier``, their registry), ``evaluation``,
``experiment``, ``export``, ``onboard`` (numpy + onnxruntime only) and ``cli`` (the command line, one module per
command; its ``detect`` and ``calibrate`` are numpy + onnxruntime only). Submodules load on first use, so
``import torchskin.onboard`` does not import torch.
"""

import importlib
from types import ModuleType

__version__ = "0.1.0"

_SUBMODULES = ("angles", "bands", "cli", "confusers", "data", "dataset", "detect", "detectors", "evaluation", "experiment",
               "export", "fit", "onboard", "optics", "render", "tissue")


def __getattr__(name: str) -> ModuleType:
    if name in _SUBMODULES:
        return importlib.import_module(f".{name}", __name__)
    raise AttributeError(f"module 'torchskin' has no attribute {name!r}")


__all__ = [*_SUBMODULES, "__version__"]
