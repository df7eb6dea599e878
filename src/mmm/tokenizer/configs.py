"""Stage 1's training settings (conf/train_stage1.yaml `loss:`, `refine:`): the tokenizer's loss
weights and the decoder refinement. Apart from the LightningModule (module.py) so that a config is
checked without loading Lightning."""

from __future__ import annotations

from dataclasses import dataclass

from mmm.config import ConfigError


@dataclass
class TokenizerLossConfig:
    position_weight: float = 0.5  # extra SmoothL1 on the root-relative joint positions
    commit_weight: float = 0.02
    # Mean distance (m) between the windows' global joint positions, the root path integrated from
    # the velocities as recover_from_ric does: small velocity errors add up along a clip.
    global_weight: float = 0.0
    root_weight: float = (
        1.0  # the reconstruction loss of the root dims (yaw and x/z velocity, height) times this
    )
    # Mean distance (m) between the decoded and the true root path (x/z) of each window, in the
    # tokenizer's own steps (the refinement has its own, refine.path_weight).
    path_weight: float = 0.0


@dataclass
class DecoderRefineConfig:
    """`steps` more optimizer steps after the tokenizer's own train the decoder alone.

    The encoder and codebook are frozen (no EMA update, no reset), so the decoder fits fixed codes
    instead of chasing a codebook that moves every step; the rate restarts at `lr` and decays to 0
    along a half cosine, and the root dims' loss is multiplied by `root_weight`. The root
    velocities' small per-clip bias is what integrates into the drift of the global root path
    (README, Stage 1); `path_weight` adds the mean distance (m) between the decoded and the true
    root path (x/z, integrated over each window as recover_from_ric does), which weighs the
    velocity errors by how far they carry the root; `start_windows` of the refinement's windows
    are the first frames of a clip (mmm.data.datasets.MotionWindowDataset says why). The module
    refines in the last `steps` of its fit; `train_stage1` runs trainer.max_steps + steps. 0: no
    refinement (the released recipe).
    """

    steps: int = 0
    lr: float = 3e-4
    root_weight: float = 25.0
    path_weight: float = 0.0
    start_windows: float = 0.0

    def __post_init__(self):
        if self.steps < 0:  # (trainer.max_steps >= 1 is TrainerConfig's own check)
            raise ConfigError(
                f"refine.steps={self.steps}: the decoder refinement's steps after trainer.max_steps steps "
                "of the whole tokenizer must be 0 or more (0: no refinement)"
            )
