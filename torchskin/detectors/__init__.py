"""Detector kinds: what a skin detector learned from generated datasets is, how it decides, how it is saved and
exported, all behind one protocol and one registry.

Modules, lowest first (each imports only those above it):

- ``features``: what every kind shares: the dataset's band columns (``BAND_COLUMNS``, from ``dataset.schema``),
  the configuration features with their units and domains, the brightness floor, the index formulas (``ratio_indices``,
  whose one home is ``torchskin.detect``), the configuration buffers and the tuning configurations.
- ``protocol``: the ``DetectorModel`` protocol (decide, domain, detector graph, checkpoint with a ``kind``), the
  optional ``BoxDetectorModel`` (per-configuration boxes) and the plain records the kinds take (``TrainRequest``,
  ``CalibrationData``).
- ``graphs``: the ONNX helpers the kinds' detector graphs are written with.
- ``boxes``, ``classifier``: the two built-in kinds (learners: they train from datasets).
- ``registry``: kind name -> model class; ``load`` / ``save`` / ``train`` / ``kind_of``. ``torchskin.evaluation``,
  ``torchskin.export``, the model cards and the command line dispatch through it.

A new kind is one module (a class that satisfies ``DetectorModel``) plus one call, ``registry.register(MyKind)``;
its ``options`` (``protocol.KindOption``) become ``torchskin train`` flags.

This package's ``__init__`` imports nothing: ``import torchskin.detectors.features`` loads no learner. Submodules
load on first use (``torchskin.detectors.registry``).
"""

import importlib
from types import ModuleType

_SUBMODULES = ("boxes", "classifier", "features", "graphs", "protocol", "registry")


def __getattr__(name: str) -> ModuleType:
    if name in _SUBMODULES:
        return importlib.import_module(f".{name}", __name__)
    raise AttributeError(f"module 'torchskin.detectors' has no attribute {name!r}")


__all__ = list(_SUBMODULES)
