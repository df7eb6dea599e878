"""What `mmm pipeline` reads (conf/pipeline.yaml): its state file and each step's overrides.

Kept apart from the steps so that a config is composed and checked without loading Lightning or
MLflow."""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import partial

from omegaconf import DictConfig

from mmm.config import ConfigError, compose
from mmm.data.configs import DataConfig
from mmm.evaluation.configs import load_evaluate_config
from mmm.registry.configs import load_promote_config
from mmm.tracking import TrackingConfig
from mmm.training.configs import (
    load_evaluator_config,
    load_length_config,
    load_stage1_config,
    load_stage2_config,
)


@dataclass
class StepOverrides:
    stage1: list[str] = field(default_factory=list)
    stage2: list[str] = field(default_factory=list)
    length: list[str] = field(default_factory=list)
    evaluator: list[str] = field(default_factory=list)
    evaluate: list[str] = field(default_factory=list)
    promote: list[str] = field(default_factory=list)
    stage1_parts: list[str] = field(default_factory=list)
    stage2_parts: list[str] = field(default_factory=list)


@dataclass
class PipelineConfig:
    state_file: str = "outputs/pipeline/state.json"
    overrides: StepOverrides = field(default_factory=StepOverrides)
    data: DataConfig = field(default_factory=DataConfig)
    logger: TrackingConfig = field(default_factory=TrackingConfig)


# StepOverrides' fields and the config each one overrides
STEP_CONFIGS = {
    "stage1": load_stage1_config,
    "stage2": load_stage2_config,
    "length": load_length_config,
    "evaluator": load_evaluator_config,
    "evaluate": load_evaluate_config,
    "promote": load_promote_config,
    "stage1_parts": partial(load_stage1_config, parts=True),
    "stage2_parts": partial(load_stage2_config, parts=True),
}


def shared_overrides(overrides: list[str]) -> list[str]:
    """The command line's data.* and logger.* overrides, which every step's config takes too."""
    return [o for o in overrides if o.split("=", 1)[0].lstrip("+~").startswith(("data.", "logger."))]


def load_pipeline_config(overrides: list[str] = ()) -> DictConfig:
    """conf/pipeline.yaml with `overrides`. Each step's own overrides (overrides.stage2=[...]) are
    composed with its config here too, so that a misspelt or out-of-range one is refused before the
    first step trains rather than when its step comes, minutes later."""
    cfg_node = compose("pipeline", list(overrides), schema=PipelineConfig)
    common = [f"data={cfg_node.data.name}", f"data.root={cfg_node.data.root}", *shared_overrides(overrides)]
    for key, load in STEP_CONFIGS.items():
        given = list(cfg_node.overrides[key])
        if given:
            try:
                load([*common, *given])
            except (ConfigError, ValueError) as e:
                raise ConfigError(f"overrides.{key}={given}: {e}") from None
    return cfg_node
