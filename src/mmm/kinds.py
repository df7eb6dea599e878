"""The catalogue of model kinds: what each trained model is, where its runs and files go, what it
is registered as and how to make one. Loading, promotion, the CLI, training and the dashboard
read these names from here.

    kind          trains                       experiment          registered as
    stage1        the motion tokenizer         mmm-stage1          mmm-tokenizer     (promote tokenizer)
    stage1-parts  the part-aware tokenizer     mmm-stage1-parts    (inside mmm-upperbody)
    stage2        the masked transformer       mmm-stage2          mmm-text2motion   (promote text2motion)
    stage2-parts  the part-aware transformer   mmm-stage2-parts    mmm-upperbody     (promote upperbody)
    length        the length estimator         mmm-length          (not registered)
    evaluator     the contrastive evaluator    mmm-evaluator       mmm-evaluator     (promote evaluator)
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class ModelKind:
    name: str  # `mmm train NAME`
    what: str  # in messages: "no <what> found"
    experiment: str  # the MLflow experiment of its training runs
    output_dir: str  # its run folders: <output_dir>/<run>/checkpoints/best.ckpt
    config: str  # conf/<config>.yaml
    train: str  # how to make one (a Make target)
    checkpoint: str  # the checkpoint family it writes (mmm.checkpoints.CHECKPOINTS)
    registered: str | None = None  # the registered model its promoted versions go to
    promote: str | None = None  # `mmm promote KIND` / conf/promote.yaml criteria.<promote>
    description: str = ""  # the experiment's description in the dashboard

    @property
    def part_aware(self) -> bool:
        return self.name.endswith("-parts")


KINDS: dict[str, ModelKind] = {
    k.name: k
    for k in (
        ModelKind(
            "stage1",
            "stage-1 model",
            "mmm-stage1",
            "outputs/stage1",
            "train_stage1",
            "make train-stage1",
            "stage1",
            "mmm-tokenizer",
            "tokenizer",
            "Stage 1: the motion tokenizer (VQ-VAE). Charts: `train/*` losses, `codebook/*` usage and "
            "resets, `collapse/*` "
            "(the collapse monitor), `val/mpjpe_root_aligned_mm` and `val/mpjpe_global_mm`. Images: "
            "`previews/reconstruction` "
            "(reference above reconstruction, one per validation: use the step slider).",
        ),
        ModelKind(
            "stage1-parts",
            "part-aware stage-1 model",
            "mmm-stage1-parts",
            "outputs/stage1-parts",
            "train_stage1_parts",
            "make train-stage1-parts",
            "stage1",
            None,
            None,
            "Stage 1 of the part-aware model (upper-body editing): two codebooks, charts per codebook "
            "(`codebook/lower/*`, `codebook/upper/*`).",
        ),
        ModelKind(
            "stage2",
            "text-to-motion model",
            "mmm-stage2",
            "outputs/stage2",
            "train_stage2",
            "make train-stage2",
            "stage2",
            "mmm-text2motion",
            "text2motion",
            "Stage 2: the masked transformer. Charts: `train/*` loss and token accuracies, `val/*`. Images: "
            "`previews/generation` "
            "(reference above generated, one per validation). Tags link the stage-1 run and registered "
            "version it was trained on.",
        ),
        ModelKind(
            "stage2-parts",
            "part-aware model",
            "mmm-stage2-parts",
            "outputs/stage2-parts",
            "train_stage2_parts",
            "make train-stage2-parts",
            "stage2",
            "mmm-upperbody",
            "upperbody",
            "Stage 2 of the part-aware model: upper-body codes from the text given the lower body.",
        ),
        ModelKind(
            "length",
            "length estimator",
            "mmm-length",
            "outputs/length",
            "train_length",
            "make train-length",
            "length",
            None,
            None,
            "The length estimator (caption -> number of codes), used when no length is given.",
        ),
        ModelKind(
            "evaluator",
            "evaluator",
            "mmm-evaluator",
            "outputs/evaluator",
            "train_evaluator",
            "make train-evaluator",
            "evaluator",
            "mmm-evaluator",
            "evaluator",
            "The package's own text-motion evaluator (contrastive), the yardstick promotion compares with.",
        ),
    )
}

STAGE1, STAGE1_PARTS, STAGE2, STAGE2_PARTS, LENGTH, EVALUATOR = (KINDS[k] for k in KINDS)

# `mmm promote KIND` -> the model kind whose runs it promotes
PROMOTABLE: dict[str, ModelKind] = {k.promote: k for k in KINDS.values() if k.promote}
