"""Configuration-dependent rules-detector boundaries: configuration features -> box (b1, b2, c1, c2, d1):
NDGRI in [b1, b2] and NDSI in [c1, c2] (the thesis's rules, eq 2.5.10, with the box chosen per configuration),
and NDVN >= d1, a visible/NIR rule on NDVN = ((g + r) - (n + s)) / (g + r + n + s), learned from generated
datasets.

Why the third rule: under eq 3.1.1 with the thesis's surface model, sunlit skin seen at grazing local
incidence (and in glints) adds a spectrally flat front-surface reflection, which pulls NDGRI and NDSI along
straight lines towards (0, 0); a box that keeps that skin must reach down in NDSI towards where litter, bark
and dry vegetation sit. Those are far darker in the visible than in the NIR (NDVN around -0.5), while skin,
from Type I to VI, stays above about -0.35, and the flat reflection only raises it towards 0. d1 is one value
for every configuration, set below the training skin's NDVN (``ndvn_rule``); with d1 = -1 the rule is inactive
(the 2-index rules alone: ``ndvn_quantile=None``).

The model is a small MLP on standardised features with an output that keeps b1 <= b2 and c1 <= c2::

    (lo_g, w_g, lo_s, w_s) -> b1 = lo_g, b2 = lo_g + softplus(w_g), c1 = lo_s, c2 = lo_s + softplus(w_s).

``hidden=0`` gives a constant box (one box for every configuration: the refitted static baseline).

Two trainers:

- ``train_boxes`` (default): per configuration, the box that covers the most sunlit skin pixels while every
  earthlib *train* spectrum stays at least ``margin`` (index units, L-infinity) outside it, for the training
  configurations and for random configurations over the training domain; a small cost per unit of box width
  keeps the edges where the skin pixels are (soft, sigmoid edges during training; hard boxes afterwards). It
  starts from the data: the conditional quantile box (``fit_quantiles``) first, then the coverage loss.
- ``train_quantiles``: the box edges as conditional quantiles of skin NDGRI and NDSI (pinball loss).

Both are followed by ``tune_false_alarms`` (a hard guarantee on the train spectra). The model is exported
to ONNX (``torchskin.export``: ``boundaries.onnx`` from ``boundaries_graph``, ``detector.onnx`` from
``BoxModel.detector_graph``, the five edge forms of ``BoxDetector``) and run onboard without torch
(``torchskin.onboard``: ``OnboardBoxes``, ``OnboardDetector``).

This package is the ``boxes`` detector kind (``torchskin.detectors.registry`` registers ``BoxModel``, its model), a
folder of modules, lowest first (each imports only those above it):

- ``rules``: the box columns, the visible/NIR rule's d1, ``inside_box`` and ``false_alarm_rate``.
- ``data``: the training rows of a generated dataset (``load_skin_rows``, ``load_scene_rows``).
- ``fit``: the trainers' losses, the quantile fit, ``BoxTraining`` and the false-alarm tuning.
- ``onnx``: ``folded``, ``boundaries_graph``, ``edge_detector_graph`` and ``BoxDetector``.
- ``model``: ``BoxModel`` and what constructs one: the trainers (``train_boxes``, ``train_quantiles``, ``learn``,
  ``train_on_dataset``) and ``save`` / ``load``.

Every public name is importable from ``torchskin.detectors.boxes`` itself.
"""

from .data import load_scene_rows, load_skin_rows
from .fit import (
    MIN_TRAIN_COVERAGE,
    BoxTraining,
    fit_quantiles,
    margin_violation,
    quantile_loss,
    scene_rate,
    scene_violation,
    soft_inside,
    train_coverage,
    tune_false_alarms,
)
from .model import METHODS, BoxModel, TrainResult, learn, load, save, train_boxes, train_on_dataset, train_quantiles
from .onnx import EDGE_C, EDGE_M, BoxDetector, boundaries_graph, edge_detector_graph, edge_matrix, folded
from .rules import BOX_ORDER, NDVN_MARGIN, NDVN_QUANTILE, false_alarm_rate, inside_box, ndvn_rule

__all__ = ["BOX_ORDER", "METHODS", "BoxDetector", "BoxModel", "BoxTraining", "EDGE_C", "EDGE_M", "MIN_TRAIN_COVERAGE",
           "NDVN_MARGIN", "NDVN_QUANTILE", "TrainResult", "boundaries_graph", "edge_detector_graph", "edge_matrix",
           "false_alarm_rate", "fit_quantiles", "folded", "inside_box", "learn", "load", "load_scene_rows",
           "load_skin_rows", "margin_violation", "ndvn_rule", "quantile_loss", "save", "scene_rate", "scene_violation",
           "soft_inside", "train_boxes", "train_coverage", "train_on_dataset", "train_quantiles", "tune_false_alarms"]
