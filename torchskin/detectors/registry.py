"""The registry of detector kinds: kind name -> model class (``protocol.DetectorModel``), and what the rest of
torchskin does with a model through it, never by testing its class: load and save checkpoints (``load``, ``save``:
every checkpoint names its kind; box checkpoints written before they did are ``boxes``), train by method
(``train``), tell a model's kind (``kind_of``) and its boxes (``boxes_of``), and find the kind a training summary
describes (``kind_for_method``: the model cards).

What a kind contributes beyond its model (``protocol``'s module docstring): its training options
(``options``: ``torchskin train`` builds a flag of each), its ``--method`` help, its onboard head, whether
``evaluation.select_detector`` may ship it, its model-card words; read here with their defaults (``options``,
``method_help``, ``onboard_head``, ``onboard_kinds``, ``card_scores``). The command line, ``torchskin.evaluation``,
``torchskin.export`` and the model cards name no kind.

The built-in kinds, ``boxes`` (``boxes.BoxModel``), ``classifier`` (``classifier.SkinClassifier``) and ``lut``
(``lut.LookupKind``), are registered when this module loads. A new kind is one module plus one call (``unregister`` removes it):

>>> from torchskin.detectors import registry
>>> sorted(registry.kinds())
['boxes', 'classifier', 'lut']
>>> registry.kind_for_method("quantiles").kind
'boxes'
>>> [o.cli_flag for o in registry.options(registry.get("boxes"))][-1], registry.onboard_kinds()
('--no-ndvn-rule', ('boxes', 'lut'))
>>> class Tiny(registry.get("classifier")):
...     kind, methods = "tiny", ("tiny",)
...     options = (registry.KindOption("level", 0.5, "tiny: the level"),)
>>> _ = registry.register(Tiny)
>>> registry.methods()[-1], registry.option_kinds()["--level"]
('tiny', 'tiny')
>>> registry.unregister("tiny")
>>> "tiny" in registry.kinds()
False
"""

from __future__ import annotations

import os
from dataclasses import replace
from typing import Any, cast

import torch

from ..bands import INDEX_BANDS_NM
from ..dataset.files import require_bands
from .boxes import BoxModel
from .classifier import SkinClassifier
from .lut import LookupKind
from .protocol import BoxDetectorModel, DetectorModel, KindOption, PipelineRun, TrainRequest, write_checkpoint

#: the kind of a checkpoint without a ``kind`` key: box checkpoints were written without one
LEGACY_KIND = "boxes"

_KINDS: dict[str, type[DetectorModel]] = {}


def register(cls: type[DetectorModel], replace: bool = False) -> type[DetectorModel]:
    """Register a detector kind under ``cls.kind`` (usable as a class decorator); its ``methods`` become training
    methods of ``train`` and ``kind_for_method``, its ``options`` flags of ``torchskin train``. ``ValueError`` when
    the name or a method is taken (unless ``replace``), when an option's flag or name is another kind's or the
    command's own, when ``onboard_head`` is not one of ``ONBOARD_HEADS``, or when the class lacks a part of
    ``DetectorModel``."""
    kind = getattr(cls, "kind", None)
    if not isinstance(kind, str) or not kind:
        raise ValueError(f"{cls.__name__} needs a class attribute kind (a non-empty string)")
    missing = [a for a in ("decide", "detector_graph", "checkpoint", "from_checkpoint", "methods") if not hasattr(cls, a)]
    if missing:
        raise ValueError(f"detector kind {kind!r} ({cls.__name__}) lacks {', '.join(missing)} (protocol.DetectorModel)")
    opts = options(cls)
    if not all(isinstance(o, KindOption) for o in opts):
        raise ValueError(f"detector kind {kind!r}: options must be protocol.KindOption")
    if getattr(cls, "onboard_head", "generic") not in ONBOARD_HEADS:
        raise ValueError(f"detector kind {kind!r}: onboard_head must be one of {', '.join(ONBOARD_HEADS)}")
    mine = [o.cli_flag for o in opts]
    common = {*COMMON_FLAGS, *(f"--{n}" for n in ("func", "command", "debug"))}
    if (len(set(mine)) != len(mine) or len({o.name for o in opts}) != len(opts)
            or {*mine, *(f"--{o.name.replace('_', '-')}" for o in opts)} & common):
        raise ValueError(f"detector kind {kind!r}: its option flags must be distinct and not torchskin train's own")
    owners = {f: k for f, k in option_kinds().items() if k != kind}  # another kind's flag or option name
    names = {o.name: k for k, c in _KINDS.items() if k != kind for o in options(c)}
    taken = {o.cli_flag: owners.get(o.cli_flag) or names[o.name] for o in opts
             if o.cli_flag in owners or o.name in names}
    if taken:
        raise ValueError(f"option(s) {', '.join(taken)} of kind {kind!r} already belong to "
                         f"{', '.join(sorted(set(taken.values())))}")
    if not replace:
        if kind in _KINDS and _KINDS[kind] is not cls:
            raise ValueError(f"detector kind {kind!r} is already registered ({_KINDS[kind].__name__})")
        taken = {m: k for k, c in _KINDS.items() if c is not cls for m in c.methods}
        clash = [m for m in cls.methods if m in taken]
        if clash:
            raise ValueError(f"training method(s) {', '.join(clash)} of kind {kind!r} already belong to "
                             f"{', '.join(sorted({taken[m] for m in clash}))}")
    _KINDS[kind] = cls
    return cls


#: the onboard runtime's heads (``onboard.detector_head``): a kind's ``onboard_head`` is one of them
ONBOARD_HEADS = ("boxes", "generic", "lut")
#: the flags ``torchskin train`` has for every kind (a kind's options may not take them)
COMMON_FLAGS = ("--data", "--out", "--method", "--steps", "--hidden", "--seed", "--pfa-budget", "--scene-budget",
                "--no-scene", "--sunlit-only", "--frames", "--json", "--help", "-h")


def options(cls: type[DetectorModel]) -> tuple[KindOption, ...]:
    """A kind's own training options (``protocol.KindOption``; none by default)."""
    return tuple(getattr(cls, "options", ()))


def option_kinds() -> dict[str, str]:
    """Every registered kind's option flags, flag -> kind name, in registration order."""
    return {o.cli_flag: k for k, c in _KINDS.items() for o in options(c)}


def method_help(cls: type[DetectorModel]) -> str:
    """The words of a kind's methods in ``torchskin train --method``'s help (default: the method names)."""
    return str(getattr(cls, "method_help", "; ".join(f"{m}: a {cls.kind} model" for m in cls.methods)))


def onboard_head(kind: str) -> str:
    """The onboard head a kind's ``detector.onnx`` runs on (its ``onboard_head``, default "generic")."""
    return str(getattr(get(kind), "onboard_head", "generic"))


def onboard_kinds() -> tuple[str, ...]:
    """The kinds whose detector graph meets the onboard budget (``onboard_selectable``), in registration order."""
    return tuple(k for k, c in _KINDS.items() if getattr(c, "onboard_selectable", False))


def onboard_cost(kind: str) -> str:
    """A kind's words for why its detector graph misses the onboard budget (its ``onboard_cost``; a kind that
    meets it, or an unknown kind, says so plainly).

    >>> onboard_cost("classifier")
    "a per-pixel MLP, ~40x the box graph's time per frame"
    """
    cls = _KINDS.get(kind)
    return str(getattr(cls, "onboard_cost", "slower than the onboard budget")) if cls is not None else \
        "not a registered kind"


def box_kinds() -> tuple[str, ...]:
    """The kinds that decide by a box per configuration (``protocol.BoxDetectorModel``), in registration order."""
    return tuple(k for k, c in _KINDS.items() if hasattr(c, "boxes") and hasattr(c, "boundaries_graph"))


def card_scores() -> tuple[str, ...]:
    """The registered kinds' model-card words for a ``detector.onnx`` score (``card_score``), in registration
    order."""
    words = (getattr(c, "card_score", None) for c in _KINDS.values())
    return tuple(str(w) for w in words if w)


def pipeline_runs() -> tuple[PipelineRun, ...]:
    """The models ``make demo``'s pipeline trains, calibrates, compares and exports: every registered kind's
    ``pipeline_runs``, in registration order (the order of ``evaluation.json``).

    >>> [r.name for r in pipeline_runs()]
    ['boundaries', 'baseline_box', 'classifier', 'lut']
    """
    return tuple(r for c in _KINDS.values() for r in getattr(c, "pipeline_runs", ()))


def unregister(kind: str) -> None:
    """Remove a registered kind (``KeyError`` if there is none of that name)."""
    del _KINDS[kind]


def kinds() -> dict[str, type[DetectorModel]]:
    """The registered kinds, name -> class (a copy)."""
    return dict(_KINDS)


def get(kind: str) -> type[DetectorModel]:
    """The class of a registered kind; ``ValueError`` naming the known kinds otherwise."""
    try:
        return _KINDS[kind]
    except KeyError:
        raise ValueError(f"unknown detector kind {kind!r}; known kinds: {', '.join(sorted(_KINDS))}") from None


def kind_of(model: Any) -> str:
    """The kind name of a model (``ValueError`` for an object that is not a registered kind's)."""
    kind = getattr(type(model), "kind", None)
    if not isinstance(kind, str) or kind not in _KINDS:
        raise ValueError(f"{type(model).__name__} is not a registered detector kind")
    return kind


def methods() -> tuple[str, ...]:
    """Every training method of the registered kinds, in registration order (``torchskin train --method``)."""
    return tuple(m for c in _KINDS.values() for m in c.methods)


def kind_for_method(method: str | None, default: str | None = LEGACY_KIND) -> type[DetectorModel]:
    """The kind a training method makes (a training summary's ``method``); an unknown or missing method gives
    ``default`` (the model cards' rule: anything that is not another kind's method is a box model), and
    ``ValueError`` with ``default=None``."""
    for c in _KINDS.values():
        if method in c.methods:
            return c
    if default is None:
        raise ValueError(f"unknown training method {method!r}; known methods: {', '.join(methods())}")
    return get(default)


def required_bands(cls: type[DetectorModel]) -> tuple[float, ...]:
    """The band centres (nm) a dataset must hold for a kind: its ``required_bands``, default the four index bands
    (``bands.INDEX_BANDS_NM``, whose columns every built-in kind reads).

    >>> required_bands(get("boxes"))
    (544.0, 633.0, 1080.0, 1580.0)
    """
    return tuple(getattr(cls, "required_bands", INDEX_BANDS_NM))


def boxes_of(model: Any) -> Any:
    """The ``boxes(config)`` function of a box kind (``protocol.BoxDetectorModel``), or None for a kind that decides
    otherwise."""
    return model.boxes if isinstance(model, BoxDetectorModel) else None


def load_checkpoint(path: str | os.PathLike) -> dict:
    """The dict of a torchskin model checkpoint (``ValueError`` with one line for anything else)."""
    try:
        ck = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises many types for junk files
        raise ValueError(f"cannot read model checkpoint {str(path)!r}: not a torch checkpoint, or truncated "
                         f"({type(e).__name__})") from None
    if not isinstance(ck, dict) or "state_dict" not in ck:
        raise ValueError(f"{str(path)!r} is not a torchskin model checkpoint")
    return ck


def load(path: str | os.PathLike, what: str = "model") -> tuple[DetectorModel, dict]:
    """The model of a torchskin checkpoint, by its ``kind`` (none: ``LEGACY_KIND``), in eval mode, and the
    checkpoint dict; ``ValueError`` with one line naming ``what`` and the file for anything else."""
    ck = load_checkpoint(path)
    kind = ck.get("kind", LEGACY_KIND)
    if not isinstance(kind, str) or kind not in _KINDS:
        raise ValueError(f"{what} {str(path)!r} is a checkpoint of an unknown detector kind {kind!r}; known kinds: "
                         f"{', '.join(sorted(_KINDS))}")
    try:
        model = _KINDS[kind].from_checkpoint(ck)
    except (KeyError, RuntimeError, TypeError, ValueError) as e:
        raise ValueError(f"{what} {str(path)!r} is not a torchskin model checkpoint: {e}") from None
    return model, ck


def save(model: DetectorModel, path: str | os.PathLike, meta: dict | None = None) -> None:
    """Write ``model``'s checkpoint with its kind (``protocol.write_checkpoint``); ``ValueError`` for a model that
    is not a registered kind's."""
    kind_of(model)
    write_checkpoint(model, path, meta)


def train(req: TrainRequest) -> tuple[DetectorModel, dict, str]:
    """``torchskin train``: the kind of ``req.method`` trains on ``req.data`` (its ``from_training``); returns the
    model, its training summary and a one-line report. ``ValueError`` for an unknown method or a kind that does not
    train from datasets."""
    cls = kind_for_method(req.method, default=None)
    fn = getattr(cls, "from_training", None)
    if fn is None:
        raise ValueError(f"detector kind {cls.kind!r} does not train from datasets")
    known = {o.name: o.default for o in options(cls)}
    other = [n for n in req.options if n not in known]
    if other:
        raise ValueError(f"--method {req.method} (kind {cls.kind!r}) has no option(s) {', '.join(other)}; its "
                         f"options: {', '.join(known) or 'none'}")
    require_bands(req.data, required_bands(cls), f"--method {req.method}")  # before anything is read or written
    return cast(tuple[DetectorModel, dict, str], fn(replace(req, options={**known, **req.options})))


register(cast(type[DetectorModel], BoxModel))
register(cast(type[DetectorModel], SkinClassifier))
register(cast(type[DetectorModel], LookupKind))

__all__ = ["COMMON_FLAGS", "LEGACY_KIND", "ONBOARD_HEADS", "box_kinds", "boxes_of", "card_scores", "get",
           "kind_for_method", "kind_of", "kinds", "load", "load_checkpoint", "method_help", "methods", "onboard_head",
           "onboard_cost", "onboard_kinds", "option_kinds", "options", "pipeline_runs", "register", "required_bands", "save", "train",
           "unregister"]
