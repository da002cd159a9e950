"""Export learned detectors to ONNX: ``boundaries.onnx`` and ``baseline_box.onnx`` (configuration (N, k) ->
boxes (N, 4)) and ``detector.onnx`` (reflectance cube (B, 4, H, W) + configuration (B, k) -> mask (B, H, W) and
score; from a model of any detector kind: each writes its own, ``DetectorModel.detector_graph``), opset 17, with metadata (band centres, units, feature order and
units, skin surface model, training manifest hash, package version; the detector kind and the band set,
centres and FWHM: ``metadata``)."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import TYPE_CHECKING

from . import __version__
from .bands import INDEX_BANDS, BandSet
from .detectors.features import FEATURE_UNITS
from .detectors.protocol import BOX_ORDER, BoxDetectorModel, DetectorModel
from .io import atomic_path

if TYPE_CHECKING:
    import onnx


def model_bands(model: DetectorModel) -> BandSet:
    """The bands a model reads, in the cube's order: its ``bands`` (a ``BandSet`` or what ``BandSet.of`` takes:
    centres and FWHM) where it has them, else its kind's ``required_bands`` (centres, monochromatic:
    ``registry.required_bands``), else the thesis's ``INDEX_BANDS`` (every built-in kind's)."""
    b = getattr(model, "bands", None)
    if b is None:
        b = getattr(model, "required_bands", None)
    return INDEX_BANDS if b is None else b if isinstance(b, BandSet) else BandSet.of(b)


def metadata(model: DetectorModel, manifest_sha256: str = "", surface: str = "") -> dict[str, str]:
    """The ONNX metadata of an exported model (any detector kind: its features and domain): its detector kind
    (``kind``: the registry's name, ``boxes``, ``classifier``, ...; the onboard runtime picks its head by it), its
    band set (``bands``: ``BandSet.to_json``, centres and FWHM, in the cube's order; ``bands_nm``: the centres
    alone, as exports before ``bands`` recorded them), band units, feature order, units and domain, box order, NDVN
    formula, skin surface model, training manifest hash, package version (every key is part of the shipped files:
    keep them as they are), and, for a kind whose onboard head its name does not tell, ``onboard_head``.

    >>> from torchskin.detectors.boxes import BoxModel
    >>> m = metadata(BoxModel())
    >>> m["kind"], BandSet.from_json(m["bands"]) == INDEX_BANDS
    ('boxes', True)
    """
    bands = model_bands(model)
    return {
        "kind": model.kind,
        "skin_surface_model": surface,
        "torchskin_version": __version__,
        "bands": bands.to_json(),
        "bands_nm": json.dumps(list(bands.centers)),
        "band_units": "nm; reflectance in [0, 1] (ELM-calibrated)",
        "features": json.dumps(list(model.features)),
        "feature_units": json.dumps([FEATURE_UNITS.get(f, "") for f in model.features]),
        "feature_domain": json.dumps([[float(lo), float(hi)] for lo, hi in model.domain.tolist()]),
        "box_order": json.dumps(list(BOX_ORDER)),
        "ndvn": "((g + r) - (n + s)) / (g + r + n + s) with (g, r, n, s) the 544, 633, 1080, 1580 nm reflectance",
        "training_manifest_sha256": manifest_sha256,
        **_head(model.kind),
    }


def _head(kind: str) -> dict[str, str]:
    """The metadata ``onboard_head`` of a kind whose head (``registry.onboard_head``) the onboard runtime would not
    tell from its name (``onboard.BOX_HEAD_KINDS``); nothing otherwise (the built-in kinds)."""
    from .detectors import registry
    from .onboard import BOX_HEAD_KINDS

    head = registry.onboard_head(kind) if kind in registry.kinds() else "generic"
    return {} if head == ("boxes" if kind in BOX_HEAD_KINDS else "generic") else {"onboard_head": head}


def detector_graph(model: DetectorModel, meta: dict[str, str]) -> onnx.ModelProto:
    """The ONNX graph cube (B, 4, H, W) + configuration (B, k) -> mask, score of a model of any detector kind (its
    ``detector_graph``: a box model's edge forms, the classifier's MLP, ...)."""
    return model.detector_graph(meta)


def export(model: DetectorModel, out_dir: str | os.PathLike, manifest_sha256: str = "", *, surface: str = "",
           baseline: BoxDetectorModel | None = None, detector: DetectorModel | None = None,
           detector_meta: dict[str, str] | None = None,
           checkpoints: dict[str, str] | None = None,
           provenance: dict[str, dict[str, str]] | None = None) -> dict[str, str]:
    """Write ``boundaries.onnx`` (``model``, a model of a box kind; none for another kind), ``baseline_box.onnx`` (``baseline``, a constant box with the same
    inputs and outputs, when given) and ``detector.onnx`` (``detector``: a model of any detector kind; default
    ``model``) into ``out_dir``, opset 17, with metadata (``metadata``). Every graph is built and checked before
    any file is written; each file is written atomically. The same models give the same bytes.

    Args:
        model: the box model of ``boundaries.onnx`` (and of ``detector.onnx`` by default), or a model of any
            other kind (``detector.onnx`` alone).
        out_dir: the output folder (created if missing).
        manifest_sha256: the training dataset's manifest hash, recorded in the metadata.
        surface: the skin surface model of the training renders ("thesis" or "conserving"), recorded likewise.
        baseline: a constant box model for ``baseline_box.onnx`` (none written without it).
        detector: the model behind ``detector.onnx``: a model of any detector kind (``detectors.registry``).
        detector_meta: extra metadata of ``detector.onnx`` (e.g. which model it is and why).
        checkpoints: per graph name ("boundaries", "baseline_box", "detector"), the checkpoint it came from
            (metadata key ``checkpoint``).
        provenance: per graph name, the metadata of its own checkpoint's world, which replace the common ones
            (``training_manifest_sha256``, ``skin_surface_model``, ``light_model`` where the checkpoint records
            it; ``mixed_worlds`` when checkpoints of
            different worlds were combined on purpose): every graph records where its own model came from,
            not ``model``'s.

    Shape:
        boundaries.onnx / baseline_box.onnx: ``config`` (N, k) -> ``boxes`` (N, 5); detector.onnx: ``cube``
        (B, 4, H, W) and ``config`` (B, k) -> ``mask`` bool and ``score`` float32, (B, H, W).

    Returns:
        ``{name: path}`` of the files written ("boundaries" for a box model, "detector" and, with ``baseline``,
        "baseline_box").
    """
    ck = checkpoints or {}

    own = provenance or {}

    def meta(m: DetectorModel, name: str) -> dict[str, str]:
        return {**metadata(m, manifest_sha256, surface), **({"checkpoint": ck[name]} if name in ck else {}),
                **own.get(name, {})}

    graphs = {}
    if isinstance(model, BoxDetectorModel):  # a kind without boxes writes detector.onnx alone
        graphs["boundaries"] = model.boundaries_graph(meta(model, "boundaries"))
    if baseline is not None:
        graphs["baseline_box"] = baseline.boundaries_graph(meta(baseline, "baseline_box"))
    det = model if detector is None else detector
    graphs["detector"] = detector_graph(det, {**meta(det, "detector"), **(detector_meta or {})})
    return write_graphs(graphs, Path(out_dir))


def write_graphs(graphs: dict, out: str | os.PathLike) -> dict[str, str]:
    """Write ``{name: onnx.ModelProto}`` as ``out/<name>.onnx`` (atomically, one by one)."""
    import onnx

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = {}
    for name, g in graphs.items():
        with atomic_path(out / f"{name}.onnx", suffix=".onnx") as tmp:
            onnx.save(g, str(tmp))
        paths[name] = str(out / f"{name}.onnx")
    return paths


def write_model_cards(out_dir: str | os.PathLike, train: dict, evaluation: dict | None = None,
                      trains: dict | None = None) -> dict[str, str]:
    """A Markdown card beside each exported model (``boundaries``, ``baseline_box``, ``detector``; metadata read
    back from the ONNX files). ``train``: the training summary of boundaries.onnx; ``trains``: per model name,
    its own (default ``train``)."""
    import onnx

    from .io import write_text
    from .modelcard import model_card

    out = Path(out_dir)
    cards = {}
    for kind in ("boundaries", "baseline_box", "detector"):
        if not (out / f"{kind}.onnx").is_file():
            continue
        meta = {p.key: p.value for p in onnx.load(str(out / f"{kind}.onnx")).metadata_props}
        cards[kind] = model_card(kind, meta, (trains or {}).get(kind, train), evaluation)
    paths = {}
    for kind, text in cards.items():  # every card rendered before any is written
        write_text(out / f"{kind}.md", text)
        paths[f"{kind}_card"] = str(out / f"{kind}.md")
    return paths
