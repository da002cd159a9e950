"""Evaluation as a library: learned skin detectors against the static thesis box on held-out data.

Modules: ``metrics`` (Pd / Pfa of any per-row decision over dataset rows, by category and bin), ``regions``
(what is measured in the (NDGRI, NDSI) plane: earthlib-test Pfa, decision-region areas, the box ROC),
``candidates`` (the models compared), ``provenance`` (dataset hash, the models' worlds), ``compare`` (the
entry point ``evaluate`` and its ``table``), ``calibration`` (held-out calibration to the false-alarm budgets),
``selection`` (the model to ship), ``figures`` (the plots; the only module that draws) and ``demo`` (the
render demo ``thesis_frame``).

``evaluate(data_dir, model_paths)`` returns the complete result ``torchskin evaluate --save`` writes.
"""

from .calibration import calibrate_to_budget
from .candidates import Candidate, load_candidate, load_candidates
from .compare import evaluate, table
from .demo import thesis_frame
from .figures import boxes_plot, compare_plot, plots, write_figures
from .metrics import MIN_REFLECTANCE, rates, row_rates
from .provenance import world_warnings
from .selection import ONBOARD_KINDS, select_detector

__all__ = ["MIN_REFLECTANCE", "ONBOARD_KINDS", "Candidate", "boxes_plot", "calibrate_to_budget", "compare_plot",
           "evaluate", "load_candidate", "load_candidates", "plots", "rates", "row_rates", "select_detector",
           "table", "thesis_frame", "world_warnings", "write_figures"]
