"""What `mmm promote` reads (conf/promote.yaml): the criteria a candidate must beat the champion
on, and how it is measured.

Kept apart from the promotion itself so that a config is composed and checked without loading
Lightning or MLflow."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from omegaconf import DictConfig

from mmm.config import ConfigError, compose, to_object
from mmm.data.configs import DataConfig
from mmm.device import check_device
from mmm.evaluation.configs import ProtocolConfig, check_samples
from mmm.kinds import PROMOTABLE
from mmm.tracking import TrackingConfig


@dataclass
class Criterion:
    metric: str
    mode: str = "min"  # min: lower is better; max: higher is better
    margin: float = 0.0  # the candidate must be better by at least this much


def criteria_errors(criteria: list[Criterion], key: str) -> list[str]:
    """What is wrong with `criteria` (configured under `key`, e.g. criteria.text2motion), one
    line per problem naming the key; empty when they are valid."""
    errors = []
    if not criteria:
        errors.append(
            f"{key} is empty: a candidate would become champion compared on nothing; name at least one "
            "metric, e.g. {metric: generated/fid, mode: min, margin: 0.0}"
        )
    for i, c in enumerate(criteria):
        at = f"{key}[{i}]"
        if not isinstance(c.metric, str) or not c.metric.strip():
            errors.append(f"{at}.metric is empty; name a metric, e.g. generated/fid")
        if c.mode not in ("min", "max"):
            errors.append(f"{at}.mode={c.mode!r} must be min (lower is better) or max (higher is better)")
        try:
            margin = float(c.margin)
        except (TypeError, ValueError):
            margin = math.nan
        if not math.isfinite(margin) or margin < 0:
            errors.append(
                f"{at}.margin={c.margin!r} must be a finite number >= 0 (how much better a candidate must be)"
            )
    return errors


@dataclass
class Criteria:
    tokenizer: list[Criterion] = field(
        default_factory=lambda: [Criterion("recon/mpjpe_root_aligned_mm", "min", 0.0)]
    )
    text2motion: list[Criterion] = field(default_factory=lambda: [Criterion("generated/fid", "min", 0.0)])
    evaluator: list[Criterion] = field(
        default_factory=lambda: [Criterion("test/r_precision_top1", "max", 0.0)]
    )
    upperbody: list[Criterion] = field(default_factory=lambda: [Criterion("upper_body/both", "max", 0.0)])


@dataclass
class UpperBodyCheck:
    max_sources: int = 12  # walk/squat clips of the split, each edited with every upper-body prompt
    lower_mask: float = 0.5
    seed: int = 0


@dataclass
class PromoteConfig:
    candidate: str | None = None  # the run to promote; default: the newest finished run of the kind
    evaluator: str | None = (
        None  # evaluator for the metrics; default: the champion evaluator, else the newest
    )
    split: str = "test"
    device: str = "cpu"
    criteria: Criteria = field(default_factory=Criteria)
    protocol: ProtocolConfig = field(default_factory=ProtocolConfig)
    upper_body: UpperBodyCheck = field(default_factory=UpperBodyCheck)
    # text2motion on labelled data: prompt adherence (adherence/*, usable as criteria) beside the protocol
    adherence: bool = True
    adherence_max_items: int | None = None
    # text2motion: captions of the split rendered, each real motion above the candidate's, logged to
    # the candidate's run as promotion/samples.gif and .png (evaluation/samples.py); 0: none
    samples: int = 4
    data: DataConfig = field(default_factory=DataConfig)
    logger: TrackingConfig = field(default_factory=TrackingConfig)

    def __post_init__(self):
        check_samples(self.samples)


def load_promote_config(overrides: list[str] = ()) -> DictConfig:
    """conf/promote.yaml with `overrides`; ConfigError naming the key when a criterion is invalid."""
    cfg_node = compose("promote", list(overrides), schema=PromoteConfig)
    check_device(cfg_node.device)
    criteria: Criteria = to_object(cfg_node.criteria)
    problems = [
        p for kind in PROMOTABLE for p in criteria_errors(getattr(criteria, kind), f"criteria.{kind}")
    ]
    if problems:
        raise ConfigError("conf/promote.yaml (with the command line's overrides): " + "; ".join(problems))
    return cfg_node
