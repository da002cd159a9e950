"""The ``lut`` detector kind: a learned skin region baked into a lookup table over the bands' coordinates and the
configuration, looked up per pixel onboard (issue 40).

The region is learned by gradient-boosted trees (LightGBM) from every normalized difference, reflectance and
brightness of the bands and from the configuration (sun zenith, camera zenith, relative azimuth). It is then
evaluated once at the centre of every cell of a table: n coordinates per pixel (the log ratios of neighbouring
bands and a brightness, read from the floats' bits; ``grid``) and one slice per configuration bin. Onboard, a pixel's
decision is one table bit: the lookup-table skin detector of colour histograms (Jones & Rehg 1999), extended over
the configuration.

Modules, lowest first: ``grid`` (coordinates, cells, configuration bins), ``model`` (``LookupModel``, the table,
and ``LookupDetector``, its ONNX graph's torch reference), ``train`` (the learner, the bake, the budgets),
``plot`` (a figure of the region) and ``kind`` (``LookupKind``: the model with its training and figure, as
registered).
"""

from .grid import cells, config_bins, coordinates
from .kind import LookupKind
from .model import LookupDetector, LookupModel

__all__ = ["LookupDetector", "LookupKind", "LookupModel", "cells", "config_bins", "coordinates"]
