"""What `mmm evaluate` and `mmm ablate` read (conf/evaluate.yaml, conf/ablate.yaml): the protocol,
the editing benchmarks' settings, the sweeps' grids and the training runs a sweep makes.

Kept apart from the code that runs them so that a config is composed and checked without loading
Lightning, torchmetrics or MLflow: a misspelt key or an out-of-range value is refused in about a
second."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

from omegaconf import DictConfig

from mmm.config import ConfigError, check_whole, compose, to_object
from mmm.data.configs import DataConfig
from mmm.device import check_device
from mmm.generation.settings import SamplingConfig
from mmm.generation.upper_body import UPPER_BODY_GUIDANCE
from mmm.tracking import TrackingConfig
from mmm.training.configs import load_stage1_config, load_stage2_config
from mmm.transformer.schedules import DECODING_SCHEDULES


def check_samples(count: int) -> None:
    if count < 0:
        raise ValueError(f"samples={count}: give the number of captions to render, 0 for none")


@dataclass
class ProtocolConfig:
    replications: int = 20
    batch_size: int = 32
    diversity_times: int = 300
    mm_texts: int = 100
    mm_generations: int = 30
    mm_times: int = 10
    max_batches: int | None = None  # cap per replication (quick runs on a CPU); None: the whole split
    seed: int = 0
    sampling: SamplingConfig = field(default_factory=SamplingConfig)

    def __post_init__(self):
        least = dict(replications=1, batch_size=1, max_batches=1, diversity_times=0, mm_texts=0)
        for name, bound in {**least, "mm_generations": 0, "mm_times": 0}.items():
            value = getattr(self, name)
            if name != "max_batches":
                check_whole(f"protocol.{name}", value, bound)
            elif value is not None:  # None: the whole split
                check_whole("protocol.max_batches", value, bound, " (or null: the whole split)")


@dataclass
class EditingConfig:
    """The editing benchmarks' settings (conf/evaluate.yaml `editing:`)."""

    inbetween_keep: float = 0.25  # inbetween: share kept at EACH end; the middle 1 - 2x is generated
    outpaint_keep: float = 0.5  # outpaint: the middle share kept; (1 - x) / 2 generated at each end
    prefix_keep: float = 0.5  # prefix: the first share kept, the rest generated
    suffix_keep: float = 0.5  # suffix: the last share kept, the first 1 - x generated
    far_frames: int = 32  # exactness "far": kept frames at least this many frames from a generated one
    with_text: bool = True  # temporal tasks: False generates without the caption (completion without text)
    lower_mask: float = 0.5  # upper-body: the share of lower-body codes hidden in the main row
    lower_masks: list[float] = field(
        default_factory=lambda: [0.0, 0.25, 0.5, 0.75, 1.0]
    )  # upper-body: the ablation sweep (one row each; [] for the main row only)
    upper_body_guidance: float | None = UPPER_BODY_GUIDANCE  # upper-body CFG; null: protocol.sampling's
    upper_body_sources: int = 12  # upper-body adherence: labelled lower-body clips edited (x 3 prompts)
    long_prompts: int = 4  # long: consecutive captions per long motion
    transition_codes: int = 2  # long: new codes between two segments
    context_codes: int = 6  # long: codes of each segment the transition sees

    def validate(self) -> None:
        """ValueError naming the setting, its value and what it may be."""
        for name, low, high in (
            ("inbetween_keep", 0.0, 0.5),
            ("outpaint_keep", 0.0, 1.0),
            ("prefix_keep", 0.0, 1.0),
            ("suffix_keep", 0.0, 1.0),
        ):
            value = getattr(self, name)
            if not low < value < high:
                raise ValueError(
                    f"editing.{name}={value}: a share of the motion strictly between {low} and {high}"
                )
        for value in [self.lower_mask, *self.lower_masks]:
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"editing lower mask {value}: a share of lower-body codes in [0, 1]")
        if self.long_prompts < 2:
            raise ValueError(
                f"editing.long_prompts={self.long_prompts}: at least 2 captions make a long motion"
            )
        if self.far_frames < 0:
            raise ValueError(f"editing.far_frames={self.far_frames}: a number of frames, 0 or more")
        for name, least, what in (
            ("transition_codes", 0, "new codes between two segments"),
            ("context_codes", 1, "codes of each segment a transition sees"),
            ("upper_body_sources", 1, "labelled clips edited"),
        ):
            check_whole(f"editing.{name}", getattr(self, name), least, f" ({what})")


@dataclass
class EvaluatorChoice:
    reference: str | None = None  # own evaluator (path, run id, models:/...; newest when null) or t2m:DIR
    glove_dir: str | None = None  # standard evaluator only
    norm_dir: str | None = None  # standard evaluator only: its mean.npy / std.npy


@dataclass
class EvaluateConfig:
    text2motion: str | None = None  # stage-2 model: path, run id, models:/NAME@ALIAS; newest when null
    task: str = "text2motion"  # text2motion | inbetween | outpaint | prefix | suffix | upper-body | long
    tokenizer: str | None = None  # for reconstruction metrics; default: the text2motion model's own
    # The stage-1 model text2motion was trained with, when the file its checkpoint records lies
    # outside outputs/ (generate's --stage1); its weights must be the ones the transformer learned.
    stage1: str | None = None
    evaluator: EvaluatorChoice = field(default_factory=EvaluatorChoice)
    split: str = "test"
    what: list[str] = field(default_factory=lambda: ["text2motion", "reconstruction", "adherence"])
    adherence_max_items: int | None = None
    # Best of N for adherence (mmm.generation.best_of): each motion the best of this many draws by
    # the judge (path, run id, models:/...; null: the evaluator champion, else the newest run).
    # The text2motion protocol always draws one: its evaluator would be judging its own choice.
    adherence_candidates: int = 1
    adherence_judge: str | None = None
    # A caption in two steps also judged clause by clause, and one with a count or speed word
    # against its counterfactuals (mmm.generation.best_of.judge_scores).
    adherence_by_clause: bool = True
    adherence_counterfactuals: bool = True
    output_dir: str = "outputs/evaluation"
    # Captions of the split rendered with their real motions (samples.gif/png; samples.py); 0: none.
    samples: int = 4
    device: str = "cpu"
    precision: str | None = None  # fp32 | bf16 | int8 decoding passes; null: the device's default
    protocol: ProtocolConfig = field(default_factory=ProtocolConfig)
    editing: EditingConfig = field(default_factory=EditingConfig)
    data: DataConfig = field(default_factory=DataConfig)
    logger: TrackingConfig = field(default_factory=TrackingConfig)


def load_evaluate_config(overrides: list[str] = ()) -> DictConfig:
    cfg_node = compose("evaluate", list(overrides), schema=EvaluateConfig)
    check_device(cfg_node.device)
    return cfg_node


@dataclass
class Grids:
    reset: list[int] = field(default_factory=lambda: [1, 20, 80])
    cross_layers: list[int] = field(default_factory=lambda: [0, 1, 2, 4])
    schedules: list[str] = field(default_factory=lambda: list(DECODING_SCHEDULES))
    iterations: list[int] = field(default_factory=lambda: [5, 10, 15])
    temperature: list[float] = field(default_factory=lambda: [0.5, 1.0, 1.2, 1.5])
    topk: list[float] = field(default_factory=lambda: [0.1, 0.5, 0.9, 1.0])
    topp: list[float] = field(default_factory=lambda: [0.1, 0.5, 0.9, 1.0])


@dataclass
class AblationConfig:
    output_dir: str = "outputs/ablations"
    text2motion: str | None = None  # the model the inference sweeps use (default: the newest stage-2 result)
    stage1: str | None = None  # the tokenizer the cross-layers sweep trains on (default: the newest)
    evaluator: str | None = None  # see mmm.evaluation.evaluators.load_evaluator
    stage1_overrides: list[str] = field(default_factory=list)  # applied to the training runs of a sweep
    stage2_overrides: list[str] = field(default_factory=list)
    device: str = "cpu"
    split: str = "test"
    # Captions drawn at every setting under their real motions (samples.gif/png); 0: none.
    samples: int = 2
    grids: Grids = field(default_factory=Grids)
    protocol: ProtocolConfig = field(default_factory=ProtocolConfig)
    data: DataConfig = field(default_factory=DataConfig)
    logger: TrackingConfig = field(default_factory=TrackingConfig)


ABLATIONS = {
    "reset": (8, "codebook reset every N iterations"),
    "cross-layers": (9, "cross-attention layers"),
    "schedule": (10, "mask schedule and iterations"),
    "temperature": (11, "temperature"),
    "topk": (12, "top-k (fraction of the codebook)"),
    "topp": (13, "top-p"),
}


def sweep_settings(kind: str, grids: Grids) -> list[tuple[str, dict]]:
    """(row label, what changes) for each setting of a sweep."""
    if kind == "reset":
        return [(f"reset every {n}", {"stage1": [f"callbacks.reset_every_n_steps={n}"]}) for n in grids.reset]
    if kind == "cross-layers":
        return [
            (f"{n} cross-attention layers", {"stage2": [f"model.transformer.num_cross_layers={n}"]})
            for n in grids.cross_layers
        ]
    if kind == "schedule":
        return [
            (f"{s}, {t} iterations", {"sampling": {"schedule": s, "max_iterations": t}})
            for s in grids.schedules
            for t in grids.iterations
        ]
    if kind == "temperature":
        return [(f"temperature {t:g}", {"sampling": {"temperature": t}}) for t in grids.temperature]
    if kind == "topk":
        return [(f"top-k {round(k * 100)}%", {"sampling": {"top_k": k}}) for k in grids.topk]
    if kind == "topp":
        return [(f"top-p {p:g}", {"sampling": {"top_p": p}}) for p in grids.topp]
    raise ValueError(f"unknown ablation {kind!r}; choose one of {', '.join(ABLATIONS)}")


def _sweep_shared(cfg: AblationConfig) -> list[str]:
    """What every training run of a sweep takes from the sweep: its data (the runs train on what the
    sweep evaluates on) and its tracking store."""
    return [
        f"data={cfg.data.name}",
        f"data.root={cfg.data.root}",
        f"logger.tracking_uri={cfg.logger.tracking_uri}",
        f"logger.artifact_root={cfg.logger.artifact_root}",
        "trainer.enable_progress_bar=false",
    ]


def sweep_stage1_overrides(cfg: AblationConfig, change: dict, run_name: str) -> list[str] | None:
    """The `mmm train stage1` overrides of a training setting; None when it trains no tokenizer."""
    if "stage1" not in change:
        return None
    return [*_sweep_shared(cfg), *cfg.stage1_overrides, *change["stage1"], f"logger.run_name={run_name}"]


def sweep_stage2_overrides(cfg: AblationConfig, change: dict, run_name: str, stage1: str | None) -> list[str]:
    """The `mmm train stage2` overrides of a training setting, on tokenizer `stage1` (None: the newest)."""
    return [
        *_sweep_shared(cfg),
        *cfg.stage2_overrides,
        *([f"stage1={stage1}"] if stage1 else []),
        *change.get("stage2", []),
        f"logger.run_name={run_name}",
    ]


def check_sweep(kind: str, rows_spec: list[tuple[str, dict]], cfg: AblationConfig) -> None:
    """Refuse a sweep with nothing to run or a setting its rows would refuse, before any run,
    folder or training exists: a training setting's stage configs are composed and checked here,
    so a misspelt `stage2_overrides` key or a grid value the transformer refuses stops the sweep
    before its first setting trains."""
    if not rows_spec:
        raise ConfigError(
            f"ablation {kind}: its grid is empty (grids.* in conf/ablate.yaml or on the command line), so "
            "there is nothing to sweep; give at least one value"
        )
    if kind == "reset":
        bad = [n for n in cfg.grids.reset if isinstance(n, bool) or not isinstance(n, int) or n < 0]
        if bad:
            raise ConfigError(f"grids.reset={bad}: reset intervals are whole numbers of steps, 0 or more")
    for label, change in rows_spec:
        if "sampling" in change:  # refused on construction, naming the setting
            SamplingConfig(**{**asdict(cfg.protocol.sampling), **change["sampling"]})
            continue
        runs = {
            "stage1": (sweep_stage1_overrides(cfg, change, "ablation-check"), load_stage1_config),
            "stage2": (sweep_stage2_overrides(cfg, change, "ablation-check", cfg.stage1), load_stage2_config),
        }
        for stage, (overrides, load) in runs.items():
            try:
                if overrides is not None:
                    load(overrides)
            except (ConfigError, ValueError) as e:
                raise ConfigError(
                    f"ablation {kind}, setting {label!r}: its {stage} training would be refused "
                    f"(stage1_overrides, stage2_overrides, grids.*): {e}"
                ) from None


def load_ablation_config(overrides: list[str] = (), kind: str | None = None) -> DictConfig:
    """conf/ablate.yaml with `overrides`; with `kind`, also refuses a sweep of that kind with an
    empty grid or a setting its rows would refuse."""
    cfg_node = compose("ablate", list(overrides), schema=AblationConfig)
    check_device(cfg_node.device)
    if kind is not None:
        cfg = to_object(cfg_node)
        check_sweep(kind, sweep_settings(kind, cfg.grids), cfg)
    return cfg_node
