"""torchskin: physics-based multispectral skin reflectance, rendering and detector adaptation in PyTorch.

Modules: ``tissue`` (9-layer Kubelka-Munk skin), ``optics`` (Fresnel, Schlick, microfacet lobe, combined
BRDF), ``detect`` (NDSI/NDGRI, rules box, Bhattacharyya), ``calibrate`` (ELM, BRDF-ELM), ``bands``, ``data``,
``scene``/``raycast``/``render`` (the renderer), ``fit``, ``dataset``, ``boundaries``, ``export`` and
``onboard`` (numpy + onnxruntime only). Submodules load on first use, so ``import torchskin.onboard`` does
not import torch.
"""

import importlib

__version__ = "0.1.0"

_SUBMODULES = ("bands", "boundaries", "calibrate", "confusers", "data", "dataset", "detect", "experiment", "export",
               "fit", "onboard", "optics", "raycast", "render", "scene", "tissue")


def __getattr__(name):
    if name in _SUBMODULES:
        return importlib.import_module(f".{name}", __name__)
    raise AttributeError(f"module 'torchskin' has no attribute {name!r}")


__all__ = [*_SUBMODULES, "__version__"]
