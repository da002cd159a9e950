"""torchskin: physics-based multispectral skin reflectance, rendering and detector adaptation in PyTorch.

Modules: ``tissue`` (9-layer Kubelka-Munk skin), ``optics`` (Fresnel, Schlick, microfacet lobe, combined
BRDF), ``detect`` (NDSI/NDGRI, rules box, Bhattacharyya), ``calibrate`` (ELM, BRDF-ELM), ``bands``, ``data``.
"""

__version__ = "0.1.0"

from . import bands, calibrate, data, detect, optics, tissue  # noqa: E402

__all__ = ["bands", "calibrate", "data", "detect", "optics", "tissue", "__version__"]
