"""Callbacks around the EMA codebooks: periodic reset of unused codes, and collapse detection.

Both handle every codebook of the tokenizer (`pl_module.quantizers`: one for the plain
tokenizer, "lower" and "upper" for the part-aware one) and log per codebook when there are
several. Both read state that the quantizer keeps identical on every rank (usage from
all-reduced counts), and the collapse decision is reduced across ranks as well, so every rank
acts at the same step.
"""

from __future__ import annotations

import json
import logging
from dataclasses import asdict, dataclass

import lightning as L
import torch
from lightning.pytorch.loggers import MLFlowLogger
from lightning.pytorch.utilities import rank_zero_warn

from mmm.step_logging import logged_batch_end
from mmm.tokenizer.quantizer import metric_name

log = logging.getLogger(__name__)


class CodebookReset(L.Callback):
    """Every `every_n_steps` optimizer steps, replace the codes no latent used since the last
    reset by latents of the current batch, in every codebook (0 disables). Logs the running total
    `codebook/codes_reset_total` (`codebook/<part>/codes_reset_total` too when there are several
    codebooks), so every logged step shows every reset so far whatever the logging interval."""

    def __init__(self, every_n_steps: int = 20):
        self.every_n_steps = every_n_steps
        self.total_reset = 0
        self.total_by_codebook: dict[str, int] = {}

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        step = trainer.global_step
        # The decoder refinement (the run's last steps) keeps the codebook fixed: nothing to reset.
        refining = getattr(pl_module, "refining", False)
        due = self.every_n_steps > 0 and step > 0 and step % self.every_n_steps == 0 and not refining
        for name, q in pl_module.quantizers.items():
            n = q.reset_unused() if due else 0
            self.total_by_codebook[name] = self.total_by_codebook.get(name, 0) + n
            self.total_reset += n
        if not logged_batch_end(trainer):
            return
        metrics = {"codebook/codes_reset_total": float(self.total_reset)}
        if len(self.total_by_codebook) > 1:
            metrics.update(
                {
                    metric_name("codebook", name, "codes_reset_total"): float(k)
                    for name, k in self.total_by_codebook.items()
                }
            )
        pl_module.log_dict(metrics, on_step=True, on_epoch=False)

    def state_dict(self) -> dict:
        return {"total_reset": self.total_reset, "total_by_codebook": dict(self.total_by_codebook)}

    def load_state_dict(self, state_dict: dict) -> None:
        self.total_reset = int(state_dict["total_reset"])
        self.total_by_codebook = {k: int(v) for k, v in state_dict.get("total_by_codebook", {}).items()}


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
    codebook: str = ""  # which one ("lower", "upper"); "" for the plain tokenizer's only codebook

    def describe(self) -> str:
        return f"{self.codebook} codebook: {self.reason}" if self.codebook else self.reason


@dataclass
class CodebookHealth:
    """What the monitor follows of one codebook."""

    usage: torch.Tensor | None = None  # (K,) assignments in the current window
    steps_in_window: int = 0
    active_fraction: float = 1.0  # of the last completed window
    perplexity: float = 0.0  # smoothed
    peak: float = 0.0
    strikes: int = 0  # consecutive steps with a collapse reason


class CollapseMonitor(L.Callback):
    """Detects codebook collapse: too few codes active over a window of steps, or the (smoothed)
    perplexity far below its peak since the warm-up (before it, the freshly seeded codebook's
    perplexity is not what a healthy one keeps), in any codebook. Acts per `action`: warn, stop (end
    the run cleanly on all ranks) or fail (raise CodebookCollapseError). Logs `collapse/*`
    metrics (`collapse/<part>/*` when there are several codebooks) and the events, which name
    the codebook."""

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
        self.min_active_fraction, self.perplexity_drop, self.smoothing, self.patience = (
            min_active_fraction,
            perplexity_drop,
            smoothing,
            patience,
        )
        self.codebooks: dict[
            str, CodebookHealth
        ] = {}  # keyed like `pl_module.quantizers`, filled at the first step
        self.events: list[CollapseEvent] = []

    @property
    def active_fraction(self) -> float:
        """The lowest active fraction of any codebook over its last completed window."""
        return min((h.active_fraction for h in self.codebooks.values()), default=1.0)

    def _update(self, health: CodebookHealth, quantizer, perplexity: float, warm: bool) -> None:
        counts = quantizer.latest_counts
        if counts is None:
            return
        health.usage = (
            counts.detach().clone() if health.usage is None else health.usage.to(counts.device) + counts
        )
        health.steps_in_window += 1
        if health.steps_in_window >= self.window_steps:
            health.active_fraction = float((health.usage > 0).float().mean())
            health.usage.zero_()
            health.steps_in_window = 0
        health.perplexity = (
            perplexity
            if health.perplexity == 0.0
            else self.smoothing * health.perplexity + (1 - self.smoothing) * perplexity
        )
        if warm:
            health.peak = max(health.peak, health.perplexity)

    def collapse_reason(self, health: CodebookHealth) -> str | None:
        if health.active_fraction < self.min_active_fraction:
            return (
                f"active codes {health.active_fraction:.2%} of the codebook over the last "
                f"{self.window_steps} steps (< {self.min_active_fraction:.2%})"
            )
        if health.peak > 0 and health.perplexity < self.perplexity_drop * health.peak:
            return (
                f"perplexity {health.perplexity:.1f} fell below {self.perplexity_drop:g} x its peak "
                f"{health.peak:.1f}"
            )
        return None

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        if getattr(pl_module, "refining", False):
            return  # the decoder refinement: a fixed codebook cannot collapse, and no usage is counted
        step = trainer.global_step
        metrics, reasons = {}, {}
        for name, quantizer in pl_module.quantizers.items():
            health = self.codebooks.setdefault(name, CodebookHealth())
            self._update(health, quantizer, pl_module.last_perplexities[name], warm=step >= self.warmup_steps)
            metrics[metric_name("collapse", name, "window_active_fraction")] = health.active_fraction
            metrics[metric_name("collapse", name, "perplexity_ratio")] = (
                health.perplexity / health.peak if health.peak else 1.0
            )
            reasons[name] = self.collapse_reason(health) if step >= self.warmup_steps else None
            health.strikes = health.strikes + 1 if reasons[name] else 0
        collapsed = [name for name in reasons if self.codebooks[name].strikes >= self.patience]
        detected = trainer.strategy.reduce_boolean_decision(bool(collapsed), all=False)
        if detected or logged_batch_end(trainer):  # a detection too: a stop makes its step the last logged
            pl_module.log_dict(metrics, on_step=True, on_epoch=False)
        if not detected:
            return
        for health in self.codebooks.values():
            health.strikes = 0
        # An event per collapsed codebook; when only another rank saw a collapse, one per codebook.
        new_events = []
        for name in collapsed or list(reasons):
            health = self.codebooks[name]
            reason = reasons[name] or "collapse detected on another rank"
            new_events.append(
                CollapseEvent(
                    step, reason, health.active_fraction, health.perplexity, health.peak, self.action, name
                )
            )
        self.events += new_events
        pl_module.log("collapse/detected", 1.0, on_step=True, on_epoch=False)
        if trainer.is_global_zero:
            _record_events(trainer, self.events, new_events)
        message = f"codebook collapse at step {step}: " + "; ".join(e.describe() for e in new_events)
        if self.action == "fail":
            raise CodebookCollapseError(message + " (callbacks.collapse.action=fail)")
        rank_zero_warn(message + ("; stopping the run" if self.action == "stop" else ""))
        if self.action == "stop":
            trainer.should_stop = True

    def state_dict(self) -> dict:
        return {
            "codebooks": {name: asdict(h) for name, h in self.codebooks.items()},
            "events": [asdict(e) for e in self.events],
        }

    def load_state_dict(self, state_dict: dict) -> None:
        # Checkpoints written before the monitor followed several codebooks hold one codebook's
        # fields at the top level.
        codebooks = state_dict.get("codebooks", {"": state_dict})
        self.codebooks = {
            name: CodebookHealth(
                usage=h["usage"],
                steps_in_window=int(h["steps_in_window"]),
                active_fraction=float(h["active_fraction"]),
                perplexity=float(h["perplexity"]),
                peak=float(h["peak"]),
                strikes=int(h["strikes"]),
            )
            for name, h in codebooks.items()
        }
        self.events = [CollapseEvent(**e) for e in state_dict["events"]]


def _record_events(trainer, events: list[CollapseEvent], latest: list[CollapseEvent]) -> None:
    """Tag the MLflow run with the latest events (one step's) and write all to
    events/collapse.json (rank 0)."""
    for event in latest:
        log.warning("collapse event: %s", json.dumps(asdict(event)))
    tag = f"step {latest[0].step}: " + "; ".join(e.describe() for e in latest)
    for logger in trainer.loggers:
        if isinstance(logger, MLFlowLogger):
            logger.experiment.set_tag(logger.run_id, "collapse", tag)
            logger.experiment.log_text(
                logger.run_id, json.dumps([asdict(e) for e in events], indent=2), "events/collapse.json"
            )
