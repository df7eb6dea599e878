"""Training steps and callbacks compute and log their on-step values only where Lightning writes
them (mmm.step_logging): the loggers must receive exactly what logging at every step gives."""

import lightning as L
import pytest
import torch
from lightning.pytorch.loggers.logger import Logger
from torch.utils.data import DataLoader, TensorDataset

from mmm.step_logging import logged_batch_end, logged_step


class RecordingLogger(Logger):
    def __init__(self):
        super().__init__()
        self.records: list[tuple[int, dict]] = []

    @property
    def name(self) -> str:
        return "recording"

    @property
    def version(self) -> int:
        return 0

    def log_hyperparams(self, params, *args, **kwargs) -> None:
        pass

    def log_metrics(self, metrics, step=None) -> None:
        self.records.append((step, {k: float(v) for k, v in metrics.items()}))


class Regression(L.LightningModule):
    """A linear fit that logs its loss and a value that costs work, every step or only on the
    steps `logged_step` names."""

    def __init__(self, gated: bool):
        super().__init__()
        self.gated = gated
        self.linear = torch.nn.Linear(3, 1)
        self.computed_at: list[int] = []

    def training_step(self, batch, batch_idx):
        x, y = batch
        loss = torch.nn.functional.mse_loss(self.linear(x), y)
        if self.gated and not logged_step(self):
            return loss
        self.computed_at.append(self.global_step)
        self.log_dict({"train/loss": loss, "train/abs_error": (self.linear(x) - y).abs().mean()})
        self.log("loss", loss, prog_bar=True, logger=False)
        return loss

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=0.1)


class WeightNorm(L.Callback):
    """Logs a value after each optimizer step, as the codebook callbacks do: every batch end, or
    only where `logged_batch_end` says."""

    def __init__(self, gated: bool):
        self.gated = gated

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        if self.gated and not logged_batch_end(trainer):
            return
        pl_module.log("train/weight_norm", pl_module.linear.weight.norm(), on_step=True, on_epoch=False)


def fit(gated: bool, steps: int, accumulate: int = 1) -> tuple[Regression, RecordingLogger]:
    torch.manual_seed(0)
    x = torch.randn(256, 3)
    data = TensorDataset(x, x @ torch.tensor([[1.0], [-2.0], [0.5]]) + 0.1 * torch.randn(256, 1))
    module, logger = Regression(gated), RecordingLogger()
    trainer = L.Trainer(
        max_steps=steps,
        log_every_n_steps=10,
        accumulate_grad_batches=accumulate,
        logger=logger,
        accelerator="cpu",
        devices=1,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        callbacks=[WeightNorm(gated)],
    )
    trainer.fit(module, DataLoader(data, batch_size=8, shuffle=False))
    return module, logger


@pytest.mark.parametrize("accumulate", [1, 2])
def test_gated_logging_gives_the_loggers_what_logging_every_step_gives(accumulate):
    _, every = fit(gated=False, steps=25, accumulate=accumulate)
    gated_module, gated = fit(gated=True, steps=25, accumulate=accumulate)
    assert [step for step, _ in every.records] == [9, 19]  # Lightning's cadence at log_every_n_steps=10
    assert gated.records == every.records
    assert all({"train/loss", "train/abs_error", "train/weight_norm"} <= set(m) for _, m in gated.records)
    # The values were computed only for the steps written (each micro-batch of an accumulated one).
    assert gated_module.computed_at == [s for s in (9, 19) for _ in range(accumulate)]


def test_outside_a_trainer_every_step_logs():
    assert logged_step(Regression(gated=True)) is True
