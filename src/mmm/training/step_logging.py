"""Which training steps log their on-step values.

Lightning writes a training step's `self.log(..., on_step=True)` values to the loggers only every
`log_every_n_steps` optimizer steps, but each `self.log` call costs its result collection about
0.6 ms on a CPU (it copies the value's metadata), and some values take work of their own: the
transformer's accuracies an argmax over the codebook, the evaluator's retrieval ranks. The
training steps of the package's LightningModules compute and log those values only where
`logged_step` says the loggers receive them, so every chart keeps the same points. No Lightning
import here: the model packages import this module.
"""

from __future__ import annotations


def logged_step(module) -> bool:
    """Whether the loggers receive the on-step values of the training step `module` (a
    LightningModule) is running now: the steps Lightning writes, those that complete the
    `log_every_n_steps`-th optimizer step (global steps 9, 19, 29, ... at 10), every step of a
    `fast_dev_run`, and a step begun once the trainer is stopping. Outside a trainer, True: a
    caller of `training_step` sees everything it logs."""
    try:
        trainer = module.trainer
    except RuntimeError:  # not attached to a Trainer
        return True
    if trainer.fast_dev_run:
        return True
    every = trainer.log_every_n_steps
    if not every:
        return False
    return (trainer.global_step + 1) % every == 0 or trainer.should_stop
