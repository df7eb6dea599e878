"""Callbacks around the EMA codebook: periodic reset of unused codes, and collapse detection.

Both read state that the quantizer keeps identical on every rank (usage from all-reduced counts),
and the collapse decision is reduced across ranks as well, so every rank acts at the same step.
"""

from __future__ import annotations

import json
import logging
from dataclasses import asdict, dataclass

import lightning as L
import torch
from lightning.pytorch.loggers import MLFlowLogger
from lightning.pytorch.utilities import rank_zero_warn

log = logging.getLogger(__name__)


class CodebookReset(L.Callback):
    """Every `every_n_steps` optimizer steps, replace the codes no latent used since the last
    reset by latents of the current batch (0 disables). Logs `codebook/codes_reset` every step."""

    def __init__(self, every_n_steps: int = 20):
        self.every_n_steps = every_n_steps
        self.total_reset = 0

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        step = trainer.global_step
        n = 0
        if self.every_n_steps > 0 and step > 0 and step % self.every_n_steps == 0:
            n = pl_module.quantizer.reset_unused()
            self.total_reset += n
        pl_module.log("codebook/codes_reset", float(n), on_step=True, on_epoch=False)

    def state_dict(self) -> dict:
        return {"total_reset": self.total_reset}

    def load_state_dict(self, state_dict: dict) -> None:
        self.total_reset = int(state_dict["total_reset"])


class CodebookCollapseError(RuntimeError):
    pass


@dataclass
class CollapseEvent:
    step: int
    reason: str
    active_fraction: float
    perplexity: float
    perplexity_peak: float
    action: str


class CollapseMonitor(L.Callback):
    """Detects codebook collapse: too few codes active over a window of steps, or the (smoothed)
    perplexity far below its running peak. Acts per `action`: warn, stop (end the run cleanly on
    all ranks) or fail (raise CodebookCollapseError). Logs `collapse/*` metrics and the event."""

    def __init__(
        self,
        action: str = "warn",
        warmup_steps: int = 200,
        window_steps: int = 50,
        min_active_fraction: float = 0.02,
        perplexity_drop: float = 0.2,
        smoothing: float = 0.9,
        patience: int = 3,
    ):
        if action not in ("warn", "stop", "fail"):
            raise ValueError(f"collapse action must be warn, stop or fail, got {action!r}")
        self.action, self.warmup_steps, self.window_steps = action, warmup_steps, window_steps
        self.min_active_fraction, self.perplexity_drop, self.smoothing, self.patience = min_active_fraction, perplexity_drop, smoothing, patience
        self.usage: torch.Tensor | None = None
        self.steps_in_window = 0
        self.active_fraction = 1.0  # of the last completed window
        self.perplexity = 0.0  # smoothed
        self.peak = 0.0
        self.strikes = 0
        self.events: list[CollapseEvent] = []

    def _update(self, quantizer, perplexity: float) -> None:
        counts = quantizer.latest_counts
        if counts is None:
            return
        self.usage = counts.detach().clone() if self.usage is None else self.usage.to(counts.device) + counts
        self.steps_in_window += 1
        if self.steps_in_window >= self.window_steps:
            self.active_fraction = float((self.usage > 0).float().mean())
            self.usage.zero_()
            self.steps_in_window = 0
        self.perplexity = perplexity if self.perplexity == 0.0 else self.smoothing * self.perplexity + (1 - self.smoothing) * perplexity
        self.peak = max(self.peak, self.perplexity)

    def collapse_reason(self) -> str | None:
        if self.active_fraction < self.min_active_fraction:
            return f"active codes {self.active_fraction:.2%} of the codebook over the last {self.window_steps} steps (< {self.min_active_fraction:.2%})"
        if self.peak > 0 and self.perplexity < self.perplexity_drop * self.peak:
            return f"perplexity {self.perplexity:.1f} fell below {self.perplexity_drop:g} x its peak {self.peak:.1f}"
        return None

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        self._update(pl_module.quantizer, pl_module.last_perplexity)
        step = trainer.global_step
        pl_module.log_dict(
            {"collapse/active_fraction": self.active_fraction, "collapse/perplexity_ratio": self.perplexity / self.peak if self.peak else 1.0},
            on_step=True, on_epoch=False,
        )
        reason = self.collapse_reason() if step >= self.warmup_steps else None
        self.strikes = self.strikes + 1 if reason else 0
        detected = trainer.strategy.reduce_boolean_decision(self.strikes >= self.patience, all=False)
        if not detected:
            return
        self.strikes = 0
        event = CollapseEvent(step, reason or "collapse detected on another rank", self.active_fraction, self.perplexity, self.peak, self.action)
        self.events.append(event)
        pl_module.log("collapse/detected", 1.0, on_step=True, on_epoch=False)
        if trainer.is_global_zero:
            _record_events(trainer, self.events)
        message = f"codebook collapse at step {step}: {event.reason}"
        if self.action == "fail":
            raise CodebookCollapseError(message + " (callbacks.collapse.action=fail)")
        rank_zero_warn(message + ("; stopping the run" if self.action == "stop" else ""))
        if self.action == "stop":
            trainer.should_stop = True

    def state_dict(self) -> dict:
        return {
            "usage": self.usage, "steps_in_window": self.steps_in_window, "active_fraction": self.active_fraction,
            "perplexity": self.perplexity, "peak": self.peak, "strikes": self.strikes, "events": [asdict(e) for e in self.events],
        }

    def load_state_dict(self, state_dict: dict) -> None:
        self.usage = state_dict["usage"]
        self.steps_in_window, self.active_fraction = int(state_dict["steps_in_window"]), float(state_dict["active_fraction"])
        self.perplexity, self.peak, self.strikes = float(state_dict["perplexity"]), float(state_dict["peak"]), int(state_dict["strikes"])
        self.events = [CollapseEvent(**e) for e in state_dict["events"]]


def _record_events(trainer, events: list[CollapseEvent]) -> None:
    """Tag the MLflow run with the latest event and write all to events/collapse.json (rank 0)."""
    latest = events[-1]
    log.warning("collapse event: %s", json.dumps(asdict(latest)))
    for logger in trainer.loggers:
        if isinstance(logger, MLFlowLogger):
            logger.experiment.set_tag(logger.run_id, "collapse", f"step {latest.step}: {latest.reason}")
            logger.experiment.log_text(logger.run_id, json.dumps([asdict(e) for e in events], indent=2), "events/collapse.json")
