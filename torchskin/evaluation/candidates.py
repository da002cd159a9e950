"""The models an evaluation compares: a ``Candidate`` per model file (torch checkpoint of any registered kind,
``boundaries.onnx`` / ``baseline_box.onnx``, ``detector.onnx``) or the static thesis box, each a
``decide(R, X) -> mask`` and, for box models, ``boxes(X)``."""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import cast

import numpy as np
import torch

from ..bands import INDEX_BANDS_NM, BandSet
from ..detect import DEFAULT_BOX
from ..detectors import registry
from ..detectors.features import FEATURES, ratio_indices
from ..detectors.protocol import DetectorModel, inside_box

#: one model path or several (``load_candidate``)
ModelPaths = str | os.PathLike | Sequence[str | os.PathLike]


@dataclass
class Candidate:
    """A detector under evaluation: ``decide(R (n, 4), X (n, k)) -> (n,) bool`` on ELM reflectance at 544, 633,
    1080, 1580 nm and configuration features; ``boxes(X) -> (n, 4)`` for box models (None otherwise); ``bands``,
    the band centres (nm) a dataset must hold for it (a kind's ``required_bands``, a graph's metadata)."""

    name: str
    kind: str  # "static", "detector" (a detector.onnx), or the kind of a checkpoint or of a boundaries.onnx
    features: list[str]
    decide: Callable
    boxes: Callable | None = None
    path: str = ""
    meta: dict = field(default_factory=dict)
    bands: tuple[float, ...] = INDEX_BANDS_NM


def _box_decide(boxes_of):
    def decide(R, X):
        g, s, v = ratio_indices(R)
        return inside_box(boxes_of(X), g, s, v)
    return decide


def static_candidate() -> Candidate:
    """The thesis's diffuse-model box, the same at every configuration."""
    box = torch.tensor([DEFAULT_BOX.b1, DEFAULT_BOX.b2, DEFAULT_BOX.c1, DEFAULT_BOX.c2])
    boxes_of = lambda X: box.expand(X.shape[0], 4)  # noqa: E731
    return Candidate("static box (thesis)", "static", list(FEATURES), _box_decide(boxes_of), boxes_of, "static")


def load_candidate(spec: str | os.PathLike) -> Candidate:
    """A candidate from a path: a torch checkpoint (.pt, any registered kind), an exported
    ``boundaries.onnx`` / ``baseline_box.onnx`` (configuration -> boxes) or a ``detector.onnx`` (cube +
    configuration -> mask), or the word "static"."""
    from pathlib import Path

    p = str(spec)
    if p == "static":
        return static_candidate()
    if Path(p).is_dir():
        what = " (a dataset: pass it as --data)" if (Path(p) / "_manifest.json").is_file() else ""
        raise ValueError(f"--model {p!r} is a folder{what}; a model file (.pt or .onnx) or 'static' is expected")
    if not Path(p).is_file():
        raise ValueError(f"--model {p!r} does not exist")
    name = Path(p).name
    if p.endswith(".onnx"):
        from ..onboard import OnboardBoxes, OnboardDetector, model_inputs

        if "cube" in model_inputs(p):
            d = OnboardDetector(p)
            decide = lambda R, X: torch.from_numpy(d.pixels(R.numpy(), X.numpy())["mask"])  # noqa: E731
            return Candidate(name, "detector", list(d.features), decide, None, p, dict(d.meta), graph_bands(d.meta))
        b = OnboardBoxes(p)
        boxes_of = lambda X: torch.from_numpy(b(np.asarray(X, dtype=np.float32))["boxes"])  # noqa: E731
        kind = b.meta.get("kind", registry.LEGACY_KIND)  # exports before graphs recorded their kind: boxes
        return Candidate(name, kind, list(b.features), _box_decide(boxes_of), boxes_of, p, dict(b.meta),
                         graph_bands(b.meta))
    model, ck = registry.load(p)
    return model_candidate(model, name, p, ck.get("meta", {}))


def model_candidate(model: DetectorModel, name: str, path: str = "", meta: dict | None = None) -> Candidate:
    """A candidate of a detector model of any registered kind (``detectors.registry``): its ``decide`` and, for a
    box kind, its ``boxes``."""
    from ..export import model_bands

    return Candidate(name, registry.kind_of(model), list(model.features), model.decide, registry.boxes_of(model),
                     path, meta or {}, model_bands(model).centers)


def graph_bands(meta: dict) -> tuple[float, ...]:
    """The band centres (nm) of an exported graph's metadata: its band set (``bands``), else ``bands_nm``, else
    the index bands (exports before graphs recorded their bands).

    >>> graph_bands({"bands_nm": "[544.0, 633.0, 1080.0, 1580.0]"})
    (544.0, 633.0, 1080.0, 1580.0)
    """
    if "bands" in meta:
        return tuple(BandSet.from_json(meta["bands"]).centers)
    return tuple(float(w) for w in json.loads(meta["bands_nm"])) if "bands_nm" in meta else INDEX_BANDS_NM


def load_candidates(model_paths: ModelPaths) -> list[Candidate]:
    """The candidates of one path or a list of paths (``load_candidate``); each takes its own features."""
    paths = model_paths_list(model_paths)
    if not paths:
        raise ValueError("evaluate needs at least one model")
    return [load_candidate(p) for p in paths]


def model_paths_list(model_paths: ModelPaths) -> list:
    """``model_paths`` as a list: one path (str, bytes, ``os.PathLike``) becomes a list of one."""
    return [model_paths] if isinstance(model_paths, (str, bytes)) or not hasattr(model_paths, "__iter__") \
        else list(cast(Sequence, model_paths))


def load_model(path: str | os.PathLike, what: str = "model") -> tuple[DetectorModel, dict]:
    """The model of a torchskin checkpoint (by the checkpoint's ``kind``: ``detectors.registry.load``) and the
    checkpoint dict; ``ValueError`` with one line naming ``what`` and the file for anything else."""
    return registry.load(path, what)


def box_function(model_path: str | os.PathLike) -> tuple[list[str], Callable]:
    """``features (N, k) -> boxes (N, 4)`` from a torch checkpoint (.pt) or an exported boundaries.onnx."""
    c = load_candidate(model_path)
    if c.boxes is None:
        raise ValueError(f"{str(model_path)!r} is not a box model (it has no per-configuration boxes)")
    return c.features, c.boxes


__all__ = ["Candidate", "ModelPaths", "box_function", "load_candidate", "load_candidates", "load_model",
           "model_candidate", "model_paths_list", "static_candidate"]
