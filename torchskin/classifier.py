"""A compatibility shim: the ``classifier`` detector kind moved to ``torchskin.detectors.classifier``; this module
re-exports its names so that ``torchskin.classifier`` imports keep working. New code imports
``torchskin.detectors.classifier`` (the model) or ``torchskin.detectors.features`` (what every kind shares), and
dispatches on kinds through ``torchskin.detectors.registry``."""

from .detectors.classifier import (  # noqa: F401 (re-exports)
    LINEAR_LATTICE,
    ClassifierDetector,
    ClassifierTraining,
    SkinClassifier,
    _earthlib_reflectance,
    fit_linear,
    load,
    load_rows,
    ratio_features,
    save,
    train_classifier,
    train_on_dataset,
    tune_threshold,
)

__all__ = ['ClassifierDetector', 'ClassifierTraining', 'LINEAR_LATTICE', 'SkinClassifier', 'fit_linear', 'load', 'load_rows', 'ratio_features', 'save', 'train_classifier', 'train_on_dataset', 'tune_threshold']
