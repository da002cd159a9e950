"""Where an evaluation's figures come from: the dataset (its path, manifest hash, render revision) and the
world each model was trained in against the dataset's (the skin surface model and the light model), said as
warnings when they differ."""

from __future__ import annotations

import os
from collections.abc import Sequence

from ..dataset.files import manifest, manifest_sha256
from ..detectors import registry
from .candidates import ModelPaths, model_paths_list

#: a model's or a dataset's world: the skin surface model of the renders and the light model (``world_of``)
WORLD_LABELS = {"surface": "skin surface model", "light_model": "light model"}


def model_world(path: str | os.PathLike) -> dict[str, str]:
    """The world a model was trained in, as far as its file records it: ``surface`` and ``light_model`` from a
    checkpoint's training summary, or ``skin_surface_model`` (and ``light_model``) from an ONNX export's metadata;
    {} for "static" (the thesis's box belongs to no dataset)."""
    p = str(path)
    if p == "static":
        return {}
    if p.endswith(".onnx"):
        import onnxruntime as ort

        meta = ort.InferenceSession(p, providers=["CPUExecutionProvider"]).get_modelmeta().custom_metadata_map
        world = {"surface": meta.get("skin_surface_model", ""), "light_model": meta.get("light_model", "")}
    else:
        train = registry.load_checkpoint(p).get("meta", {})
        world = {"surface": str(train.get("surface", "")), "light_model": str(train.get("light_model", ""))}
    return {k: v for k, v in world.items() if v}


def dataset_world(data_dir: str | os.PathLike) -> dict[str, str]:
    """The world a dataset was rendered in (its manifest: the skin surface model and the light model)."""
    from ..dataset.files import dataset_surface

    world = {"surface": dataset_surface(data_dir), "light_model": str((manifest(data_dir) or {}).get("light_model", ""))}
    return {k: v for k, v in world.items() if v}


def world_warnings(data_dir: str | os.PathLike, model_paths: Sequence[str | os.PathLike]) -> list[str]:
    """One sentence per model whose recorded world (``model_world``) differs from the dataset's
    (``dataset_world``): its figures on these data describe another world than the one it was trained in."""
    data = dataset_world(data_dir)
    out = []
    for path in model_paths:
        own = model_world(path)
        diff = [f"{WORLD_LABELS[k]} {own[k]} (the data: {data[k]})" for k in WORLD_LABELS
                if k in own and k in data and own[k] != data[k]]
        if diff:
            out.append(f"{path} was trained under another world than {data_dir}: " + ", ".join(diff)
                       + "; its figures here do not describe the world it was made for")
    return out


def render_revision(data_dir: str | os.PathLike):
    """The render revision the dataset's manifest records (None without one)."""
    return (manifest(data_dir) or {}).get("render_revision")


def provenance(data_dir: str | os.PathLike, model_paths: ModelPaths) -> dict:
    """The provenance fields of an evaluation result: ``warnings`` (``world_warnings``; only when there are
    any), ``data`` (the folder as given), ``data_manifest_sha256`` and ``model`` (the first model's path)."""
    paths = model_paths_list(model_paths)
    out: dict = {}
    warnings = world_warnings(data_dir, paths)  # a model of another world: said, not refused
    if warnings:
        out["warnings"] = warnings
    out["data"] = str(data_dir)
    out["data_manifest_sha256"] = manifest_sha256(data_dir)
    out["model"] = str(paths[0])
    return out


__all__ = ["WORLD_LABELS", "dataset_world", "model_world", "provenance", "render_revision", "world_warnings"]
