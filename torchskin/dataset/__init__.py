"""Randomized datasets, lowest module first: ``schema`` (the columns, their version and ``Rows``), ``files`` (the
folder's files, the manifest's checks, ``read_valid`` / ``read_rows``), ``verify`` (``torchskin dataset verify``),
``config`` (configuration sampling), ``rows`` (a pose group's rows), ``images`` (its full reflectance cubes),
``ray_backend`` (the Ray backend) and ``generate`` (the renderer's groups, shards, manifest and the local backend).

This ``__init__`` imports nothing: ``import torchskin.dataset.files`` (every reader) or ``.verify`` loads neither
torch nor the renderer. The configuration names below load ``config`` on first use.
"""

from __future__ import annotations

import importlib
from typing import Any

_SUBMODULES = ("config", "files", "generate", "images", "ray_backend", "rows", "schema", "verify")
_CONFIG_NAMES = ("PoseGroup", "default_config", "load_config", "resolve_config", "sample_group")


def __getattr__(name: str) -> Any:
    if name in _SUBMODULES:
        return importlib.import_module(f".{name}", __name__)
    if name in _CONFIG_NAMES:
        return getattr(importlib.import_module(".config", __name__), name)
    raise AttributeError(f"module 'torchskin.dataset' has no attribute {name!r}")


__all__ = [*_CONFIG_NAMES, *_SUBMODULES]
