"""What training keeps in its checkpoints: best.ckpt and last.ckpt (`checkpoint_callbacks`,
configured by `CheckpointConfig`, the `callbacks.checkpoint` section), and `RunState`, what a
resumed run needs beyond Lightning's own state."""

from __future__ import annotations

import logging
import random
from pathlib import Path

import lightning as L
import numpy as np
import torch
from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.loggers import MLFlowLogger

from mmm.callbacks.configs import CheckpointConfig
from mmm.checkpoints import FINGERPRINT_KEY
from mmm.fingerprint import tensors_fingerprint
from mmm.optim import final_drop_step

log = logging.getLogger(__name__)


def checkpoint_callbacks(directory: Path, cfg: CheckpointConfig) -> tuple[ModelCheckpoint, ModelCheckpoint]:
    """best.ckpt (by the monitored metric) and last.ckpt (at every validation), overwritten in
    place when a run resumes (no last-v1.ckpt)."""
    best = ModelCheckpoint(
        dirpath=directory,
        filename="best",
        monitor=cfg.monitor,
        mode=cfg.mode,
        save_top_k=1,
        auto_insert_metric_name=False,
        enable_version_counter=False,
    )
    last = ModelCheckpoint(
        dirpath=directory, filename="last", monitor=None, save_top_k=1, enable_version_counter=False
    )
    return best, last


# Optimizer settings the restored optimizer state would silently override (warmup, milestones and
# gamma take effect: the schedule is rebuilt from the config).
RESTORED_OPTIM_KEYS = ("lr", "betas", "weight_decay")


class RunState(L.Callback):
    """Keeps in every checkpoint what Lightning does not: the MLflow run id (a resumed run goes on
    logging to the same run), the random generators' states (it goes on drawing the same
    numbers) and the data position's meaning (batch size, world size), in types that load with
    weights_only=True. On resume it refuses what would silently change the run: another global
    batch (batch size x world size; unless `restart_epoch`), optimizer settings the restored
    optimizer state would override, or a step count that moves optim.final_share's rate drop
    across the checkpoint's step. The same global batch split over another number of processes
    resumes exactly where it stopped."""

    def __init__(self, batch_size: int | None = None, restart_epoch: bool = False):
        self.batch_size, self.restart_epoch = batch_size, restart_epoch

    def on_save_checkpoint(self, trainer, pl_module, checkpoint: dict) -> None:
        for logger in trainer.loggers:
            if isinstance(logger, MLFlowLogger):
                checkpoint["mlflow_run_id"] = logger.run_id
        np_state = np.random.get_state()
        checkpoint["rng"] = {
            "torch": torch.get_rng_state(),
            "numpy": [
                np_state[0],
                torch.from_numpy(np_state[1].astype(np.int64)),
                int(np_state[2]),
                int(np_state[3]),
                float(np_state[4]),
            ],
            "python": random.getstate(),
        }
        checkpoint["data_position"] = {"batch_size": self.batch_size, "world_size": trainer.world_size}
        # What placed optim.final_share's rate drop (a resume with another count would move it).
        checkpoint["schedule_steps"] = int(trainer.max_steps)
        # The weights' own fingerprint: every load checks it (mmm.checkpoints.load_checkpoint).
        checkpoint[FINGERPRINT_KEY] = tensors_fingerprint(checkpoint.get("state_dict") or {})

    def check_resume(self, trainer, pl_module, checkpoint: dict) -> None:
        """Raise ValueError when resuming `checkpoint` would silently change the run (see the class)."""
        self._check_progress(trainer, checkpoint)
        self._check_weights(pl_module, checkpoint)
        self._check_optimizer(pl_module, checkpoint)
        self._check_final_drop(trainer, pl_module, checkpoint)
        self._check_data_position(trainer, checkpoint)

    def on_load_checkpoint(self, trainer, pl_module, checkpoint: dict) -> None:
        self.check_resume(trainer, pl_module, checkpoint)
        rng = checkpoint.get("rng")
        if rng is None:
            return
        torch.set_rng_state(rng["torch"])
        name, keys, pos, has_gauss, cached = rng["numpy"]
        np.random.set_state((name, keys.numpy().astype(np.uint32), pos, has_gauss, cached))
        version, state, gauss = rng["python"]
        random.setstate((version, tuple(state), gauss))

    @staticmethod
    def _check_progress(trainer, checkpoint: dict) -> None:
        """Refuse a resume with nothing left to train: Lightning would stop at once, upload the
        same checkpoints again and report no validation."""
        step, max_steps = checkpoint.get("global_step"), getattr(trainer, "max_steps", None)
        if step is None or max_steps is None or max_steps < 0 or step < max_steps:
            return
        raise ValueError(
            f"nothing to resume: the checkpoint is at step {step} and this fit ends at step {max_steps} "
            "(trainer.max_steps), so the run is complete; raise trainer.max_steps to train on"
        )

    @staticmethod
    def _check_weights(pl_module, checkpoint: dict) -> None:
        """Refuse weights that do not fit the module (another model size or variant, or another
        stage's checkpoint) before Lightning's load fails halfway and marks the run FAILED."""
        saved = checkpoint.get("state_dict") or {}
        ours = pl_module.state_dict()
        missing = sorted(set(ours) - set(saved))
        unexpected = sorted(set(saved) - set(ours))
        reshaped = [
            f"{k} {tuple(saved[k].shape)} in the checkpoint, {tuple(ours[k].shape)} now"
            for k in sorted(set(ours) & set(saved))
            if tuple(saved[k].shape) != tuple(ours[k].shape)
        ]
        if not (missing or unexpected or reshaped):
            return

        def some(keys: list[str]) -> str:
            return ", ".join(keys[:3]) + (f" and {len(keys) - 3} more" if len(keys) > 3 else "")

        problems = [
            *([f"{len(missing)} weights missing ({some(missing)})"] if missing else []),
            *([f"{len(unexpected)} unknown weights ({some(unexpected)})"] if unexpected else []),
            *([f"{len(reshaped)} of another shape ({some(reshaped)})"] if reshaped else []),
        ]
        raise ValueError(
            f"cannot resume: the checkpoint's weights do not fit the model this config builds "
            f"({'; '.join(problems)}); the model settings (model=..., model.*) changed since it was written, "
            "or it is another stage's checkpoint: resume with the settings it was trained with, or start a "
            "new run (without --resume)"
        )

    @staticmethod
    def _check_optimizer(pl_module, checkpoint: dict) -> None:
        saved = (checkpoint.get("hyper_parameters") or {}).get("optim") or {}
        ours = (getattr(pl_module, "hparams", None) or {}).get("optim") or {}
        changed = [
            f"optim.{k}: {saved[k]} in the checkpoint, {ours[k]} now"
            for k in RESTORED_OPTIM_KEYS
            if k in saved and k in ours and list(np.atleast_1d(saved[k])) != list(np.atleast_1d(ours[k]))
        ]
        if changed:
            raise ValueError(
                f"cannot resume with changed optimizer settings ({'; '.join(changed)}): the checkpoint's "
                "optimizer state would override "
                "them silently; resume with the checkpoint's values, or start a new run (without --resume) "
                "to train with new ones"
            )

    @staticmethod
    def _check_final_drop(trainer, pl_module, checkpoint: dict) -> None:
        """Refuse a resume whose trainer.max_steps moves optim.final_share's rate drop across the
        checkpoint's step (the rate would jump back up, or drop at once); a drop moved within the
        steps still to come is said in the log."""
        steps, step = checkpoint.get("schedule_steps"), checkpoint.get("global_step")
        if steps is None or step is None:
            return  # a checkpoint from before the step count was recorded

        def schedule(optim: dict, total: int) -> tuple[list[int], int | None]:
            share = optim.get("final_share") or 0.0
            drop = final_drop_step(total, share) if share and total > 0 else None
            return sorted([*optim.get("milestones", []), *([drop] if drop is not None else [])]), drop

        saved_optim = (checkpoint.get("hyper_parameters") or {}).get("optim") or {}
        saved, saved_drop = schedule(saved_optim, steps)
        our_optim = (getattr(pl_module, "hparams", None) or {}).get("optim") or {}
        ours, our_drop = schedule(our_optim, trainer.max_steps)
        if saved_drop == our_drop:
            return  # explicit milestones, warm-up and gamma take effect as configured

        def where(drop: int | None, whose: str, total: int) -> str:
            at = "no drop in" if drop is None else f"its drop at step {drop} of"
            return f"{at} {whose} fit of {total} steps"

        before, now = where(saved_drop, "the checkpoint's", steps), where(our_drop, "this", trainer.max_steps)
        change = f"optim.final_share places {before} and {now}"
        if sum(m <= step for m in saved) != sum(m <= step for m in ours):
            raise ValueError(
                f"cannot resume at step {step}: {change}, so the learning rate would change at once; "
                f"resume with a fit of {steps} steps (trainer.max_steps, with refine.steps for a tokenizer), "
                f"or keep the checkpoint's schedule with optim.milestones=[{','.join(map(str, saved))}] "
                "optim.final_share=0 and any trainer.max_steps"
            )
        log.info("resuming at step %d: %s", step, change)

    def _check_data_position(self, trainer, checkpoint: dict) -> None:
        saved = checkpoint.get("data_position")
        if not saved:
            return  # a checkpoint from before the data position was recorded
        now = {"batch_size": self.batch_size, "world_size": trainer.world_size}
        changed = [
            f"{k} {saved[k]} in the checkpoint, {now[k]} now"
            for k in ("batch_size", "world_size")
            if saved.get(k) is not None and now[k] is not None and saved[k] != now[k]
        ]
        if not changed:
            return
        if None not in (saved.get("batch_size"), saved.get("world_size"), self.batch_size):
            if saved["batch_size"] * saved["world_size"] == self.batch_size * trainer.world_size:
                # Rank r takes every world-th index of the epoch's permutation, so after k steps of a
                # global batch G the ranks together have used its first k*G indices whatever the
                # split: the position carries over and every later step sees the same samples.
                log.info(
                    "resuming with %s: the same global batch (%d), so the same samples at every step",
                    "; ".join(changed),
                    self.batch_size * trainer.world_size,
                )
                return
        if not self.restart_epoch:
            raise ValueError(
                f"cannot resume mid-epoch with a changed global batch ({'; '.join(changed)}): the "
                "position in the epoch would point at other batches; resume with data.batch_size x "
                "devices x num_nodes as in the checkpoint (e.g. twice the batch size on half the "
                "processes), or add trainer.resume_restart_epoch=true to start the interrupted epoch over"
            )
        fit_state = checkpoint.get("loops", {}).get("fit_loop", {}).get("state_dict", {})
        for loader_state in fit_state.get("combined_loader", []):
            if isinstance(loader_state, dict) and "batches" in loader_state:
                loader_state["batches"] = 0  # the epoch restarts at its first batch
        log.warning(
            "resuming with %s: trainer.resume_restart_epoch=true, the interrupted epoch starts over",
            "; ".join(changed),
        )
