"""The ``lut`` kind as the registry knows it: ``LookupModel`` with its training (``train``) and its figure
(``plot``), which import the model and are imported here, above it."""

from __future__ import annotations

from typing import Any

import torch

from ..protocol import TrainRequest
from .model import LookupModel
from .plot import region_plot
from .train import train_on_dataset


class LookupKind(LookupModel):
    """``LookupModel`` with ``from_training`` (``torchskin train --method lut``) and ``region_figure``: the class
    ``detectors.registry`` registers as the ``lut`` kind (checkpoints load as it)."""

    @classmethod
    def from_training(cls, req: TrainRequest) -> tuple[LookupModel, dict, str]:
        """``torchskin train --method lut`` (``train.train_on_dataset``)."""
        return train_on_dataset(req)

    @classmethod
    def region_figure(cls, model_path: Any, data_dir: Any, out: Any) -> None:
        """A figure of the decision region of the checkpoint ``model_path`` over the dataset ``data_dir``
        (``plot.region_plot``): ``make demo`` writes ``lut_region.png``. ``ValueError`` for another kind's."""
        ck = torch.load(model_path, map_location="cpu", weights_only=True)
        if not isinstance(ck, dict) or ck.get("kind") != "lut":
            raise ValueError(f"{str(model_path)!r} is not a lut checkpoint")
        region_plot(cls.from_checkpoint(ck), data_dir, out)


__all__ = ["LookupKind"]
