"""The ``DetectorModel`` protocol every detector kind satisfies, the optional ``BoxDetectorModel`` (kinds whose
decision region is a box per configuration), and the plain records the kinds take from their callers
(``TrainRequest`` from the command line, ``CalibrationData`` from ``torchskin.evaluation``).

A kind is a class (usually an ``nn.Module``) with:

- ``kind``: its name, stored in its checkpoints (``registry.save``) and reported by ``torchskin evaluate``;
- ``methods``: the training methods (``torchskin train --method``) that make it;
- ``features`` and ``domain``: the configuration features it takes and their training domain ((k, 2));
- ``decide(R, config)``: the skin mask of ELM reflectance (n, 4) (``BAND_COLUMNS`` order) under configurations
  (n, k);
- ``detector_graph(meta)``: its ``detector.onnx`` (cube (B, 4, H, W) + config (B, k) -> mask, score), ``meta`` the
  ONNX metadata;
- ``checkpoint(meta)`` and ``from_checkpoint(ck)``: its torch checkpoint dict (without ``kind``: the registry adds
  it) and back.

What a kind contributes to the command line and the exports, class attributes with defaults (``registry``):

- ``options``: its own training options (``KindOption``), each a ``torchskin train`` flag, refused with another
  kind's ``--method``; ``registry.train`` hands them, defaults filled in, to ``from_training`` as
  ``TrainRequest.options`` (default: none);
- ``method_help``: the words of its methods in ``torchskin train --method``'s help (default: the method names);
- ``onboard_head``: the onboard runtime head its ``detector.onnx`` runs on (``onboard.detector_head``): "boxes"
  (box edge forms) or "generic" (default: any graph, per tile);
- ``onboard_selectable``: whether its detector graph meets the onboard budget, so that
  ``evaluation.select_detector`` may ship it as ``detector.onnx`` (default False);
- ``onboard_cost``: why its graph misses the onboard budget, in words, where it does (``select_detector``'s
  reason names it);
- ``card_score``: the model card's words for its ``detector.onnx`` score (default: none);
- ``pipeline_runs``: the models of it that ``make demo``'s pipeline trains, calibrates and compares
  (``PipelineRun``; default: none).

Everything else is optional, and found on the class when it is there:

- ``required_bands``: the band centres (nm) a dataset must hold for it (``registry.required_bands``; default the
  four index bands, ``bands.INDEX_BANDS_NM``): ``torchskin train`` and ``evaluate`` refuse a dataset without them;
- ``boxes(config)`` and ``boundaries_graph(meta)`` (``BoxDetectorModel``): a box per configuration;
- ``from_training(req)`` (a classmethod): ``torchskin train --method`` for the kind's methods (``TrainRequest``);
- ``calibrate_to_budget(data, scene_budget, pfa_budget, iters)``: ``evaluation.calibrate_to_budget``
  (``CalibrationData``);
- ``reference_detector()``: the torch module its ``detector.onnx`` computes;
- ``card_use`` and ``card_false_alarms(train, f)``: the model card's words for the kind;
- ``region_figure(model_path, data_dir, out)``: a figure of its decision region over a dataset, which ``make demo``
  writes as ``<name>_region.png`` beside the exports.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar, Protocol, runtime_checkable

import torch

from ..detect import rules_detector

if TYPE_CHECKING:
    import onnx


@runtime_checkable
class DetectorModel(Protocol):
    """A detector kind (see the module docstring)."""

    kind: ClassVar[str]
    methods: ClassVar[tuple[str, ...]]
    features: tuple[str, ...]

    @property
    def domain(self) -> torch.Tensor:
        """The training domain (k, 2) of the configuration features: (low, high) per feature."""
        ...

    def decide(self, R: torch.Tensor, config: torch.Tensor) -> torch.Tensor:
        """Skin mask (n,) bool of reflectance ``R`` (n, 4) under configurations ``config`` (n, k)."""
        ...

    def detector_graph(self, meta: dict[str, str]) -> onnx.ModelProto:
        """The ONNX graph cube (B, 4, H, W) + config (B, k) -> ``mask`` bool and ``score`` float32 (B, H, W),
        with ``meta`` as its metadata."""
        ...

    def checkpoint(self, meta: dict) -> dict:
        """The torch checkpoint dict (``state_dict``, what ``from_checkpoint`` needs, ``meta``)."""
        ...

    @classmethod
    def from_checkpoint(cls, ck: dict) -> DetectorModel:
        """The model (eval mode) of a checkpoint dict written from ``checkpoint``."""
        ...


@runtime_checkable
class BoxDetectorModel(DetectorModel, Protocol):
    """A kind whose decision region is a box per configuration: ``boxes(config)`` (n, k) -> (n, 4 or 5),
    (b1, b2, c1, c2[, d1]) (``BOX_ORDER``). ``torchskin.evaluation`` measures its false alarms and areas on
    the boxes, draws its ROC by scaling them, and ``torchskin export`` writes them as ``boundaries.onnx``."""

    def boxes(self, config: torch.Tensor) -> torch.Tensor:
        """The boxes (n, 4 or 5) of configurations (n, k) (no graph)."""
        ...

    def boundaries_graph(self, meta: dict[str, str]) -> onnx.ModelProto:
        """The ONNX graph config (N, k) -> boxes (N, 5), with ``meta`` as its metadata."""
        ...


#: the columns of a box of a ``BoxDetectorModel``: NDGRI min, NDGRI max, NDSI min, NDSI max, NDVN min
BOX_ORDER = ("b1_ndgri_min", "b2_ndgri_max", "c1_ndsi_min", "c2_ndsi_max", "d1_ndvn_min")


def inside_box(boxes: torch.Tensor, g: torch.Tensor, s: torch.Tensor, v: torch.Tensor | None = None) -> torch.Tensor:
    """The rules detector (eq 2.5.10 with a box per configuration): whether (NDGRI, NDSI) = (``g``, ``s``) lies in
    the box, b1 <= g <= b2 and c1 <= s <= c2 (edges included), and, with ``v`` (NDVN) and a fifth column,
    NDVN >= d1. The box test itself is ``detect.rules_detector``'s (the onboard runtime's is the exported
    detector graph).

    Args:
        boxes: (b1, b2, c1, c2[, d1]) on axis 1 (``BOX_ORDER``).
        g, s: NDGRI and NDSI.
        v: NDVN (None: the fifth rule is not applied).

    Shape:
        boxes: (N, 4 or 5, ...); g, s, v and the result: broadcast with ``boxes[:, 0]``, e.g. (N, ...).

    Returns:
        A bool tensor, True inside.

    >>> boxes = torch.tensor([[-0.5, 0.0, 0.3, 0.9, -0.4]])
    >>> inside_box(boxes, torch.tensor([-0.3, 0.2]), torch.tensor([0.6, 0.6]))
    tensor([ True, False])
    >>> inside_box(boxes, torch.tensor([-0.3]), torch.tensor([0.6]), torch.tensor([-0.6]))
    tensor([False])
    """
    ok = rules_detector(g, s, torch.movedim(boxes[:, :4], 1, -1))  # eq 2.5.10's test, the box on the last axis
    if v is not None and boxes.shape[1] > 4:
        ok = ok & (v >= boxes[:, 4])
    return ok


def false_alarm_rate(boxes: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Per box (N, 4 or 5): the fraction of ``points`` (n, 2 or 3: NDGRI, NDSI[, NDVN]) inside it."""
    v = points[:, 2][None] if points.shape[1] > 2 else None
    return inside_box(boxes[:, :, None], points[:, 0][None], points[:, 1][None], v).float().mean(-1)



@dataclass(frozen=True)
class KindOption:
    """One training option of a detector kind (its ``options``): the ``torchskin train`` flag ``flag`` (default
    ``--`` + ``name`` with dashes), read by the kind as ``TrainRequest.options[name]``. ``value_type`` is the
    flag's value type (``float``, the default, ``int``, ``str``); ``bool`` makes a switch without a value, which
    sets ``not default`` (a default-True option is a ``--no-...`` flag).

    Attributes:
        name: the option's key in ``TrainRequest.options`` (and the parsed namespace's attribute).
        default: its value when the flag is not given.
        help: the flag's help text.
        flag: the command-line flag (default ``"--" + name.replace("_", "-")``).

    >>> KindOption("width_cost", 0.05, "cost per unit of box width").cli_flag
    '--width-cost'
    """

    name: str
    default: Any
    help: str
    value_type: Callable[[str], Any] = float
    flag: str = ""

    @property
    def cli_flag(self) -> str:
        """The ``torchskin train`` flag of the option."""
        return self.flag or "--" + self.name.replace("_", "-")


@dataclass(frozen=True)
class PipelineRun:
    """One model a kind contributes to ``make demo``'s pipeline (its ``pipeline_runs``; ``registry.pipeline_runs``
    lists them all): ``scripts/pipeline_train.py`` writes ``WORK/<name>.trained.pt`` with ``torchskin train
    <args>``, ``pipeline_evaluate.py`` calibrates it to ``WORK/<name>.pt`` and compares it, and
    ``pipeline_export.py`` keeps the checkpoint and, with ``export_flag``, hands it to ``torchskin export`` by that
    flag (``--model``: ``boundaries.onnx``; ``--baseline``: ``baseline_box.onnx``).

    >>> PipelineRun("tiny", ("--method", "tiny")).checkpoint
    'tiny.pt'
    """

    name: str
    args: tuple[str, ...]
    export_flag: str | None = None

    @property
    def checkpoint(self) -> str:
        """The calibrated checkpoint's file name in the pipeline's work folder."""
        return f"{self.name}.pt"


@dataclass(frozen=True)
class TrainRequest:
    """What ``torchskin train`` asks of a kind (``registry.train``): the dataset, the method and the options of the
    command line (each kind reads those it has; defaults are the command's).

    Attributes:
        data: the generated dataset folder.
        method: the training method (``registry.methods()``).
        pfa_budget: the false-alarm budget on the earthlib train spectra, in [0, 1).
        scene_budget: the largest share of the dataset's non-skin pixels called skin, in [0, 1).
        use_scene: hold the dataset's non-skin pixels to ``scene_budget`` (False: the earthlib spectra only).
        sunlit_only: learn from sunlit skin only.
        frames: the frames to learn from (``dataset.files.FRAME_SETS``): "line" (the command's default), every
            frame whose panels are sunlit and whose empirical line is a line, also where the panels receive less
            light than sun-facing surfaces; "physical", only the frames evaluation uses (``elm_valid``).
        hidden, steps, seed: network width, optimisation steps, seed.
        options: the kind's own options (its ``options``, ``KindOption.name`` -> value); ``registry.train`` fills
            in the defaults of those not given and refuses names the kind does not have.
    """

    data: str | os.PathLike
    method: str = "boxes"
    pfa_budget: float = 1e-3
    scene_budget: float = 1e-4
    use_scene: bool = True
    sunlit_only: bool = False
    frames: str = "line"
    hidden: int = 32
    steps: int = 1500
    seed: int = 0
    options: Mapping[str, Any] = field(default_factory=dict)


@dataclass
class CalibrationData:
    """The validation rows a kind calibrates itself on (``evaluation.calibrate_to_budget``).

    Attributes:
        R: ELM reflectance (n, 4); X: configurations (n, k).
        ndgri, ndsi, ndvn: the rows' indices (n,) (the dataset's NDGRI and NDSI columns, NDVN from ``R``).
        cfg_X: one row per distinct configuration (c, k).
        nonskin: the non-skin rows (n,) bool; bright: rows above the brightness floor (n,) bool.
        test_R: the earthlib test spectra (m, 4); test_bright: those above the floor (m,) bool;
        test_pts: their (NDGRI, NDSI, NDVN) (m, 3), NaN where not bright.
    """

    R: torch.Tensor
    X: torch.Tensor
    ndgri: torch.Tensor
    ndsi: torch.Tensor
    ndvn: torch.Tensor
    cfg_X: torch.Tensor
    nonskin: torch.Tensor
    bright: torch.Tensor
    test_R: torch.Tensor
    test_bright: torch.Tensor
    test_pts: torch.Tensor


def write_checkpoint(model: DetectorModel, path: str | os.PathLike, meta: dict | None = None) -> None:
    """Write ``model``'s checkpoint with its ``kind`` first (``{"kind": ..., **model.checkpoint(meta)}``),
    atomically through a buffer: the same model gives the same bytes."""
    from ..io import save_torch

    save_torch(path, {"kind": model.kind, **model.checkpoint(meta or {})})


__all__ = ["BOX_ORDER", "BoxDetectorModel", "CalibrationData", "DetectorModel", "KindOption", "PipelineRun", "TrainRequest",
           "false_alarm_rate", "inside_box", "write_checkpoint"]
