"""Which training steps log their on-step values.

Lightning writes the `log(..., on_step=True)` values of a training step to the loggers only every
`log_every_n_steps` optimizer steps, but each `log` call costs its result collection a few
tenths of a millisecond on a CPU (it copies the value's metadata), and some values take work of
their own: the transformer's accuracies an argmax over the codebook, the evaluator's retrieval
ranks. The package's training steps and callbacks compute and log those values only where the
functions below say the loggers receive them, so every chart keeps the same points; between
those steps `trainer.callback_metrics` holds the training values of the last logged one. No
Lightning import here: the model packages import this module.
"""

from __future__ import annotations


def logged_step(module) -> bool:
    """In `training_step` (before the optimizer step): whether the loggers receive the on-step
    values of the step `module` (a LightningModule) is running, those completing the
    `log_every_n_steps`-th optimizer step (global steps 9, 19, 29, ... at 10). Outside a trainer,
    True: a caller of `training_step` sees everything it logs."""
    try:
        trainer = module.trainer
    except RuntimeError:  # not attached to a Trainer
        return True
    return _written(trainer, trainer.global_step + 1)


def logged_batch_end(trainer) -> bool:
    """The same in a callback's `on_train_batch_end`, where the batch's optimizer step has
    already counted in `trainer.global_step`."""
    return _written(trainer, trainer.global_step)


def _written(trainer, optimizer_steps: int) -> bool:
    """Lightning's rule: every `log_every_n_steps`-th optimizer step, every step of a
    `fast_dev_run`, and the step at which the trainer stops."""
    if trainer.fast_dev_run:
        return True
    every = trainer.log_every_n_steps
    if not every:
        return False
    return optimizer_steps % every == 0 or trainer.should_stop
