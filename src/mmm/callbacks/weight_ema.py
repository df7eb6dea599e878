"""An exponential moving average of the weights, which is what validation, the previews, the
adherence curve and the checkpoints see (`callbacks.weight_ema` of stage 2).

Lightning's EMAWeightAveraging does the averaging (after every optimizer step), the swap around
each validation, and the checkpoint layout: `state_dict` holds the average (what generation loads),
`current_model_state` the weights training goes on from, so a resumed run continues both. Added
here: the weights' fingerprint is of the average (the file's `state_dict`), and the decay is
recorded (`WEIGHT_EMA_KEY`) so that a resume with another setting is refused instead of continuing
silently from the average (`check_resume_ema`). Only the parameters are averaged; buffers such as
the codebook are constants and stay bit-exact. Under DDP every rank holds the same weights after
each step, so every rank's average is the same without communication.
"""

from __future__ import annotations

from lightning.pytorch.callbacks import EMAWeightAveraging

from mmm.callbacks.configs import check_weight_ema
from mmm.checkpoints import FINGERPRINT_KEY, WEIGHT_EMA_KEY
from mmm.fingerprint import tensors_fingerprint


def check_resume_ema(checkpoint: str, recorded: float | None, decay: float) -> None:
    """Refuse to resume `checkpoint` (averaged with `recorded`, None: not averaged) with another
    decay: without the average Lightning would go on training from the averaged weights, and with
    another decay the run would not be the one its config says."""
    recorded = float(recorded or 0.0)
    if recorded == float(decay):
        return
    raise ValueError(
        f"{checkpoint}: this run "
        + (f"averaged its weights with decay {recorded}" if recorded else "did not average its weights")
        + f", but callbacks.weight_ema={decay}; resume with callbacks.weight_ema={recorded} (as it was "
        "trained), or start a new run without --resume"
    )


class WeightEMA(EMAWeightAveraging):
    """EMAWeightAveraging of the parameters with `decay` from the first step; the checkpoint's
    fingerprint and `WEIGHT_EMA_KEY` describe the average it stores. Put it after the callbacks that
    should see the average at validation (it swaps the weights back at the end of the epoch)."""

    def __init__(self, decay: float):
        if not check_weight_ema(decay):
            raise ValueError(
                f"WeightEMA(decay={decay!r}): a decay of 0 averages nothing; leave the callback out"
            )
        super().__init__(decay=decay, use_buffers=False)
        self.decay = float(decay)

    def on_save_checkpoint(self, trainer, pl_module, checkpoint: dict) -> None:
        super().on_save_checkpoint(trainer, pl_module, checkpoint)
        if self._average_model is None:  # outside a fit: Lightning stored the module's own weights
            return
        checkpoint[WEIGHT_EMA_KEY] = self.decay
        checkpoint[FINGERPRINT_KEY] = tensors_fingerprint(checkpoint.get("state_dict") or {})
