"""Randomized datasets: configuration sampling (``config``). Generation, shards and backends follow."""

from .config import PoseGroup, default_config, load_config, resolve_config, sample_group

__all__ = ["PoseGroup", "default_config", "load_config", "resolve_config", "sample_group"]
