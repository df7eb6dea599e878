"""Stage 1: quantizer semantics, the module, callbacks, DDP agreement, resume, MLflow tracking."""

import contextlib
import logging
import warnings
from pathlib import Path

import lightning as L
import numpy as np
import pytest
import torch
from mlflow.tracking import MlflowClient

from mmm.callbacks.codebook import CodebookCollapseError, CodebookReset, CollapseMonitor
from mmm.config import ConfigError
from mmm.data import datamodule
from mmm.motion.features import recover_from_ric, recover_root_rot_pos
from mmm.optim import OptimConfig, cosine_tail, warmup_step_schedule
from mmm.tokenizer.configs import DecoderRefineConfig, TokenizerLossConfig
from mmm.tokenizer.module import TokenizerModule
from mmm.tokenizer.network import MotionTokenizer, TokenizerConfig
from mmm.tokenizer.quantizer import EMAQuantizer
from mmm.training.common import LIGHTNING_ADVERT, LIGHTNING_NOISE_WARNINGS, quiet_lightning
from mmm.training.configs import load_stage1_config
from mmm.training.stage1 import train_stage1
from tests.helpers import run_ddp_worker


def test_quantizer_initializes_from_latents_and_quantizes_to_nearest():
    torch.manual_seed(0)
    q = EMAQuantizer(num_codes=8, code_dim=4, decay=1.0)  # decay 1: the seeded codes stay put
    z = torch.randn(2, 4, 8)  # 16 latents >= 8 codes
    out = q(z)
    assert bool(q.initialized)
    flat = z.permute(0, 2, 1).reshape(-1, 4)
    # Every code is one of the latents.
    assert all(((flat - c).norm(dim=-1).min() < 1e-6) for c in q.codebook.clone())
    expected = torch.cdist(flat, q.codebook).argmin(-1).view(2, 8)
    assert torch.equal(out.indices, q.quantize(z))
    assert out.indices.shape == (2, 8) and out.quantized.shape == (2, 4, 8)
    q.eval()
    assert torch.equal(q.quantize(z), expected)


def test_ema_update_and_reset_semantics():
    q = EMAQuantizer(num_codes=4, code_dim=2, decay=0.5)
    q.codebook.copy_(torch.tensor([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0], [10.0, 10.0]]))
    q.ema_sum.copy_(q.codebook)
    q.ema_count.fill_(1.0)
    q.initialized.fill_(True)
    z = torch.tensor([[1.0, 0.0], [0.0, 1.0], [9.0, 0.0]]).t().unsqueeze(0)  # (1, 2, 3): codes 0, 0, 1
    q.train()
    out = q(z)
    assert out.indices.tolist() == [[0, 0, 1]]
    # count_0 = 0.5*1 + 0.5*2 = 1.5, sum_0 = 0.5*0 + 0.5*(1,1) -> code 0 = (1/3, 1/3)
    assert torch.allclose(q.codebook[0], torch.tensor([1 / 3, 1 / 3]))
    assert torch.allclose(q.codebook[1], torch.tensor([9.5, 0.0]))
    assert torch.allclose(q.codebook[2], torch.tensor([0.0, 10.0]))  # unused: count and sum both halve
    assert q.window_usage.tolist() == [2.0, 1.0, 0.0, 0.0] and q.window_active() == 2
    assert torch.equal(q.latest_counts, torch.tensor([2.0, 1.0, 0.0, 0.0]))
    torch.manual_seed(1)
    n = q.reset_unused()
    assert n == 2 and q.window_usage.sum() == 0
    latents = z[0].t()
    for k in (2, 3):  # reset codes are latents of the batch, with re-seeded EMA statistics
        assert min((latents - q.codebook[k]).norm(dim=-1)) < 1e-6
        assert q.ema_count[k] == 1.0 and torch.equal(q.ema_sum[k], q.codebook[k])
    kept = q.codebook[2].clone()
    q(torch.tensor([[1.0, 0.0]]).t().unsqueeze(0))  # nothing assigned to code 2 ...
    assert torch.allclose(q.codebook[2], kept)  # ... and it survives the update


def test_state_lives_in_buffers():
    q = EMAQuantizer(num_codes=16, code_dim=4)
    assert {"codebook", "ema_sum", "ema_count", "window_usage", "initialized"} <= set(dict(q.named_buffers()))
    assert not list(q.parameters())


def test_tokenizer_shapes_and_paper_size():
    tiny = MotionTokenizer(263, TokenizerConfig(width=32, num_codes=64))
    tiny.train()
    out = tiny(torch.randn(2, 64, 263))
    assert out.reconstruction.shape == (2, 64, 263) and out.indices.shape == (2, 16)
    assert tiny.encode(torch.randn(3, 196, 263)).shape == (3, 49)
    assert tiny.decode(torch.zeros(3, 49, dtype=torch.long)).shape == (3, 196, 263)
    paper = MotionTokenizer(263, TokenizerConfig())
    assert paper.codebook.shape == (8192, 32)
    assert 17e6 < sum(p.numel() for p in paper.parameters()) < 19e6


def test_under_a_bfloat16_autocast_the_convolutions_run_in_bfloat16_and_the_rest_in_float32():
    torch.manual_seed(0)
    tok = MotionTokenizer(263, TokenizerConfig(width=16, num_codes=32, code_dim=8)).train()
    x = torch.randn(4, 32, 263)
    conv_dtypes = []
    tok.decoder.net[0].register_forward_hook(lambda m, i, o: conv_dtypes.append(o.dtype))
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = tok(x)
        loss = torch.nn.functional.smooth_l1_loss(out.reconstruction, x) + out.commit_loss
    loss.backward()
    assert conv_dtypes == [torch.bfloat16]
    # The losses, the root integration and the codebook read float32 (README, Stage 1).
    assert out.reconstruction.dtype == out.commit_loss.dtype == torch.float32
    assert tok.quantizer.codebook.dtype == tok.quantizer.ema_sum.dtype == torch.float32
    assert all(p.grad is not None and p.grad.dtype == torch.float32 for p in tok.encoder.parameters())
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert tok.decode(out.indices).dtype == torch.float32
        lengths = torch.tensor([8, 5, 8, 3])
        assert tok.decode_lengths(out.indices, lengths).dtype == torch.float32


def test_lr_schedule_warmup_and_decay():
    f = warmup_step_schedule(1000, [200_000], 0.05)
    assert f(0) == pytest.approx(1 / 1000) and f(499) == pytest.approx(0.5) and f(999) == 1.0
    assert f(199_999) == 1.0 and f(200_000) == pytest.approx(0.05)


def test_cosine_tail_follows_the_schedule_then_decays_from_its_scale_to_zero():
    f = cosine_tail(warmup_step_schedule(10, [50], 0.1), start=60, steps=40, scale=0.3)
    assert f(4) == pytest.approx(0.5) and f(55) == pytest.approx(0.1)  # the schedule before the tail
    assert f(60) == pytest.approx(0.3) and f(80) == pytest.approx(0.15) and f(100) == pytest.approx(0.0)
    assert f(90) == pytest.approx(0.3 * 0.5 * (1 + np.cos(np.pi * 0.75)))


def test_final_share_places_one_more_milestone_from_the_run_length():
    demo = OptimConfig(warmup_steps=100, milestones=[], gamma=0.1, final_share=0.25)
    assert demo.milestones_for(1000) == [750] and demo.milestones_for(3000) == [2250]
    f = warmup_step_schedule(100, demo.milestones_for(1000), demo.gamma)
    assert f(749) == 1.0 and f(750) == pytest.approx(0.1) and f(999) == pytest.approx(0.1)
    # At least one step, rounded before the ceiling (0.3 x 10 is 3.0000000000000004), merged in order.
    assert OptimConfig(milestones=[], final_share=0.01).milestones_for(6) == [5]
    assert OptimConfig(milestones=[], final_share=0.3).milestones_for(10) == [7]
    assert OptimConfig(milestones=[2, 9], final_share=0.5).milestones_for(10) == [2, 5, 9]
    assert OptimConfig(milestones=[8]).milestones_for(None) == [8]  # unset: the run length is not needed
    with pytest.raises(ValueError, match=r"optim.final_share=0.25 needs a run of known length, got None"):
        demo.milestones_for(None)
    for share in (1.0, -0.1):
        with pytest.raises(ValueError, match=rf"optim.final_share={share}: .* must be in \[0, 1\)"):
            OptimConfig(final_share=share)


class RecordRefinement(L.Callback):
    """The tokenizer's state and the learning rate when the refinement begins, and every rate."""

    def __init__(self):
        self.at_start, self.rates = None, []

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        self.rates.append(trainer.optimizers[0].param_groups[0]["lr"])
        if trainer.global_step == pl_module.refine_start:
            self.at_start = {k: v.detach().clone() for k, v in pl_module.tokenizer.state_dict().items()}
            reset = next(c for c in trainer.callbacks if isinstance(c, CodebookReset))
            self.resets_at_start = reset.total_reset


@pytest.mark.parametrize("part_aware", [False, True])
def test_decoder_refinement_trains_the_decoder_alone_for_the_last_fraction_of_the_steps(part_aware):
    torch.manual_seed(0)
    data = torch.randn(128, 64, 263)
    module = TokenizerModule(
        263,
        TokenizerConfig(width=32, num_codes=64, part_aware=part_aware),
        OptimConfig(lr=1e-3, warmup_steps=2),
        TokenizerLossConfig(),
        refine=DecoderRefineConfig(steps=8, lr=5e-4, root_weight=25.0),
    )
    record, reset = RecordRefinement(), CodebookReset(2)
    _fit(module, data, [reset, CollapseMonitor(warmup_steps=2, window_steps=2), record], 20)
    assert module.refine_start == 12 and module.hparams["refine"]["steps"] == 8
    assert record.at_start is not None and reset.total_reset == record.resets_at_start > 0
    end = module.tokenizer.state_dict()
    frozen = [k for k in end if "decoder" not in k.split(".")]
    assert sum(k.endswith("quantizer.codebook") for k in frozen) == (2 if part_aware else 1)
    assert any("encoder" in k.split(".") for k in frozen)
    for key in frozen:  # encoder weights, codebook and its EMA statistics stand still
        assert torch.equal(end[key], record.at_start[key]), key
    trained = [k for k in end if "decoder" in k.split(".") and not torch.equal(end[k], record.at_start[k])]
    assert len(trained) > 10
    # The rate restarts at refine.lr and decays along a half cosine: step 12 of the 8-step tail, ...
    assert record.rates[12] == pytest.approx(5e-4)
    assert record.rates[16] == pytest.approx(2.5e-4) and record.rates[11] == pytest.approx(1e-3)


def test_root_path_integrates_the_root_velocity_in_metres():
    mean, std = torch.linspace(-0.5, 0.5, 263), torch.linspace(0.5, 2.0, 263)
    module = TokenizerModule(263, TokenizerConfig(width=8, num_codes=16), {}, {}, mean=mean, std=std)
    raw = torch.zeros(1, 6, 263)
    raw[..., 1], raw[..., 2] = 0.03, 0.1  # x/z metres per frame in the heading frame, no turn
    path = module.root_path((raw - mean) / std)
    expected = torch.arange(6.0)[:, None] * torch.tensor([0.03, 0.1])
    assert path.shape == (1, 6, 2) and torch.allclose(path[0], expected, atol=1e-5)
    raw[..., 0] = torch.tensor([0.2, 0.0, -0.1, 0.3, 0.0, 0.0])  # turning: the path recover_from_ric gives
    turned = module.root_path((raw - mean) / std)
    assert torch.allclose(turned, recover_from_ric(raw)[..., 0, [0, 2]], atol=1e-5)
    assert not torch.allclose(turned, path, atol=1e-3)


def test_root_path_of_the_root_features_equals_de_normalizing_all_and_has_no_gradient_elsewhere():
    mean, std = torch.linspace(-0.5, 0.5, 263), torch.linspace(0.5, 2.0, 263)
    module = TokenizerModule(263, TokenizerConfig(width=8, num_codes=16), {}, {}, mean=mean, std=std)
    x = torch.randn(3, 16, 263, generator=torch.Generator().manual_seed(0), requires_grad=True)
    path = module.root_path(x)
    _, root = recover_root_rot_pos((x * std + mean).float())  # what it computed before: all 263
    assert torch.equal(path, root[..., [0, 2]] * module.skeleton.unit_scale)
    (grad,) = torch.autograd.grad(path.square().sum(), x)
    assert grad[..., :4].abs().sum() > 0 and torch.count_nonzero(grad[..., 4:]) == 0


def test_decoder_refinement_adds_the_root_path_distance_times_its_weight():
    torch.manual_seed(0)
    module = TokenizerModule(
        263,
        TokenizerConfig(width=16, num_codes=16),
        {},
        {},
        refine=DecoderRefineConfig(steps=4, path_weight=0.3),
    )
    module.tokenizer(torch.randn(4, 64, 263))  # the codebook seeds itself from the first latents
    logged = {}
    module.log_dict = lambda metrics, **kw: logged.update(metrics)
    module.log = lambda *a, **kw: None
    batch = torch.randn(4, 64, 263)
    with_path = module._refine_step(batch)
    module.refine_cfg.path_weight = 0.0
    without = module._refine_step(batch)
    with torch.no_grad():
        recon = module.tokenizer.reconstruct(module.tokenizer.encode(batch))
        distance = (module.root_path(recon) - module.root_path(batch)).norm(dim=-1).mean()
    assert float(distance) > 0.01
    assert float((with_path - without).detach()) == pytest.approx(0.3 * float(distance), rel=1e-4)
    # Logged by the first step, the one with the path loss.
    assert float(logged["train/root_path_m"]) == pytest.approx(float(distance), rel=1e-4)


def test_the_tokenizer_steps_add_the_root_path_distance_times_loss_path_weight():
    torch.manual_seed(0)
    module = TokenizerModule(263, TokenizerConfig(width=16, num_codes=16), {}, {"path_weight": 0.2})
    module.tokenizer(torch.randn(4, 64, 263))  # the codebook seeds itself from the first latents
    module.tokenizer.eval()  # no EMA update or reset between the two steps below
    logged = {}
    module.log_dict = lambda metrics, **kw: logged.update(metrics)
    module.log = lambda *a, **kw: None
    batch = torch.randn(4, 64, 263)
    with_path = module.training_step(batch, 0)
    with_path_logged, logged = logged, {}
    module.loss_cfg.path_weight = 0.0
    without = module.training_step(batch, 0)
    with torch.no_grad():
        recon = module.tokenizer(batch).reconstruction
        distance = (module.root_path(recon) - module.root_path(batch)).norm(dim=-1).mean()
    assert float(distance) > 0.01
    assert float((with_path - without).detach()) == pytest.approx(0.2 * float(distance), rel=1e-4)
    assert float(with_path_logged["train/root_path_m"]) == pytest.approx(float(distance), rel=1e-4)
    assert "train/root_path_m" not in logged


def test_the_refinement_switches_its_windows_to_clip_starts():
    from mmm.data.datasets import MotionWindowDataset

    torch.manual_seed(0)
    motions = [np.random.default_rng(i).standard_normal((80, 263)).astype(np.float32) for i in range(4)]
    data = MotionWindowDataset(
        motions, np.zeros(263, np.float32), np.ones(263, np.float32), start_windows=0.5
    )
    module = TokenizerModule(
        263,
        TokenizerConfig(width=16, num_codes=16),
        OptimConfig(warmup_steps=1),
        {},
        refine=DecoderRefineConfig(steps=4, start_windows=0.5),
    )

    class Phase(L.Callback):
        seen: list[bool] = []

        def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
            self.seen.append(data.at_start)

    _fit(module, data, [Phase()], 10)
    assert Phase.seen == [False] * 6 + [True] * 4  # switched when the refinement (steps 6-9) begins


def test_decoder_refinement_needs_a_step_budget(walker_dataset, tmp_path):
    module = TokenizerModule(
        263, TokenizerConfig(width=8, num_codes=16), {}, {}, refine=DecoderRefineConfig(steps=4)
    )
    with pytest.raises(ValueError, match=r"refine.steps=4 with a fit of max_steps=4: .*budget"):
        _fit(module, torch.randn(8, 16, 263), [], 4)
    # The rest is refused when the config is loaded, before a trainer (or Lightning) is imported.
    with pytest.raises(ConfigError, match=r"refine.steps=-1: .*0 or more \(0: no refinement\)"):
        load_stage1_config(_stage1_overrides(walker_dataset, tmp_path, 4, **{"refine.steps": -1}))
    # Lightning would train forever at -1 and nothing at 0, and divide by zero at an interval of 0.
    for key, value in (("max_steps", -1), ("max_steps", 0), ("val_check_interval", 0)):
        with pytest.raises(ConfigError, match=rf"trainer.{key}={value}: must be a whole number of at least"):
            load_stage1_config([*_stage1_overrides(walker_dataset, tmp_path, 4), f"trainer.{key}={value}"])
    # A negative reset interval used to turn the resets off silently.
    no_resets = {"callbacks.reset_every_n_steps": -5}
    with pytest.raises(ConfigError, match=r"callbacks.reset_every_n_steps=-5: must be a whole number, 0 or"):
        load_stage1_config(_stage1_overrides(walker_dataset, tmp_path, 4, **no_resets))
    for key, value, fix in (
        ("batch_size", 0, "at least 1"),
        ("window", 0, "at least 4"),
        ("window", 30, "data.unit_length=4 .* data.window=28"),
    ):
        with pytest.raises(ConfigError, match=rf"data.{key}={value}[: ].*{fix}"):
            load_stage1_config([*_stage1_overrides(walker_dataset, tmp_path, 4), f"data.{key}={value}"])


@pytest.mark.slow
def test_stage1_runs_its_steps_then_the_refinement_steps(walker_dataset, tmp_path):
    result = train_stage1(
        load_stage1_config(_stage1_overrides(walker_dataset, tmp_path, 6, **{"refine.steps": 4}))
    )
    ckpt = torch.load(result.last_checkpoint, map_location="cpu", weights_only=True)
    assert ckpt["global_step"] == 10 and ckpt["hyper_parameters"]["refine"]["steps"] == 4
    client = MlflowClient(f"sqlite:///{tmp_path}/mlflow.db")
    params = client.get_run(result.run_id).data.params
    assert (params["trainer.max_steps"], params["refine.steps"]) == ("6", "4")  # as the user set them
    assert not result.stopped_early


def test_a_stage1_fit_reads_and_reports_each_split_once(walker_dataset, tmp_path, monkeypatch):
    """train_stage1 sets the data up before the fit (for the statistics) and the fit sets it up
    again: that second call read every clip again and printed each split's report twice."""
    reported = []
    log_report = datamodule._log_report
    monkeypatch.setattr(
        datamodule, "_log_report", lambda what, report: (reported.append(what), log_report(what, report))
    )
    result = train_stage1(load_stage1_config(_stage1_overrides(walker_dataset, tmp_path, 5)))
    assert Path(result.best_checkpoint).is_file()
    assert [what.split()[-2:] for what in reported] == [["train", "clips"], ["val", "clips"]]


@contextlib.contextmanager
def _lightning_output():
    """(lines, warnings): what Lightning's rank-zero logger logs and every warning raised in the block."""
    lines = []
    handler = logging.Handler()
    handler.emit = lambda record: lines.append(record.getMessage())
    rank_zero_log = logging.getLogger("lightning.pytorch.utilities.rank_zero")
    rank_zero_log.addHandler(handler)
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            yield lines, caught
    finally:
        rank_zero_log.removeHandler(handler)


def test_a_fit_prints_no_lightning_advert_or_known_noise_and_every_other_line(walker_dataset, tmp_path):
    """Lightning's cloud-logger advert, the model summary's bfloat16 note and torch's pytree
    deprecation are dropped during a fit (`quiet_lightning`); its other lines and warnings are not."""
    with _lightning_output() as (lines, caught):
        bf16 = {"trainer.precision": "bf16-mixed"}  # the model summary would warn about it
        train_stage1(load_stage1_config(_stage1_overrides(walker_dataset, tmp_path, 5, **bf16)))
    assert any(line.startswith("GPU available") for line in lines), lines
    assert not any(line.startswith(LIGHTNING_ADVERT) for line in lines), lines
    messages = [str(w.message) for w in caught]
    assert not [m for m in messages if any(noise in m for noise in LIGHTNING_NOISE_WARNINGS)], messages
    # Outside a fit nothing is filtered.
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        warnings.warn(LIGHTNING_NOISE_WARNINGS[0], UserWarning)
    assert len(caught) == 1 and not logging.getLogger("lightning.pytorch.utilities.rank_zero").filters


def test_quiet_lightning_drops_only_its_own_lines():
    rank_zero_log = logging.getLogger("lightning.pytorch.utilities.rank_zero")
    with _lightning_output() as (lines, caught):
        with quiet_lightning():
            for message in LIGHTNING_NOISE_WARNINGS:
                warnings.warn(f"{message} (and more)", UserWarning)
            warnings.warn("a warning of the run's own", UserWarning)
            rank_zero_log.info(f"{LIGHTNING_ADVERT} install something")
            rank_zero_log.info("GPU available: False, used: False")
        rank_zero_log.info(f"{LIGHTNING_ADVERT} after the fit")
    assert [str(w.message) for w in caught] == ["a warning of the run's own"]
    assert lines == ["GPU available: False, used: False", f"{LIGHTNING_ADVERT} after the fit"]


def _fit(module, data, callbacks, steps):
    trainer = L.Trainer(
        max_steps=steps,
        callbacks=callbacks,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        limit_val_batches=0,
        accelerator="cpu",
        enable_model_summary=False,
    )
    trainer.fit(module, torch.utils.data.DataLoader(data, batch_size=16, shuffle=True))
    return trainer


class DegenerateEncoder(torch.nn.Module):
    """Every latent the same: all tokens fall into one code."""

    def forward(self, x):
        return torch.zeros(x.shape[0], 32, x.shape[2] // 4) + 0.0 * x.mean()


@pytest.mark.slow
def test_collapse_is_detected_and_a_healthy_run_is_not():
    torch.manual_seed(0)
    data = torch.randn(256, 64, 263)
    healthy = TokenizerModule(
        263, TokenizerConfig(width=32, num_codes=64), OptimConfig(warmup_steps=5), TokenizerLossConfig()
    )
    monitor = CollapseMonitor(action="fail", warmup_steps=10, window_steps=5, min_active_fraction=0.1)
    _fit(healthy, data, [CodebookReset(5), monitor], 40)
    assert monitor.events == [] and monitor.active_fraction > 0.5

    degenerate = TokenizerModule(
        263, TokenizerConfig(width=32, num_codes=64), OptimConfig(warmup_steps=5), TokenizerLossConfig()
    )
    degenerate.tokenizer.encoder = DegenerateEncoder()
    warn = CollapseMonitor(
        action="warn", warmup_steps=10, window_steps=5, min_active_fraction=0.1, patience=2
    )
    with pytest.warns(UserWarning, match="codebook collapse at step"):
        _fit(degenerate, data, [warn], 30)
    assert warn.events and warn.events[0].step >= 10 and warn.active_fraction == pytest.approx(1 / 64)

    stop = CollapseMonitor(
        action="stop", warmup_steps=10, window_steps=5, min_active_fraction=0.1, patience=2
    )
    degenerate.tokenizer.quantizer.initialized.fill_(False)
    with pytest.warns(UserWarning, match="stopping the run"):
        trainer = _fit(degenerate, data, [stop], 100)
    assert trainer.global_step < 100 and stop.events[0].action == "stop"

    fail = CollapseMonitor(
        action="fail", warmup_steps=10, window_steps=5, min_active_fraction=0.1, patience=2
    )
    with pytest.raises(CodebookCollapseError, match="active codes 1.56%"):
        _fit(degenerate, data, [fail], 100)


@pytest.mark.slow
def test_resetting_every_iteration_churns_the_codebook():
    """Supplementary C: a reset every iteration keeps replacing codes (the paper reports collapse
    and divergence); every 20 steps leaves a stable codebook."""
    torch.manual_seed(0)
    data = torch.randn(256, 64, 263)
    counts = {}
    for every in (1, 20):
        module = TokenizerModule(
            263, TokenizerConfig(width=32, num_codes=64), OptimConfig(warmup_steps=5), TokenizerLossConfig()
        )
        reset = CodebookReset(every)
        _fit(module, data, [reset], 40)
        counts[every] = reset.total_reset
    assert counts[1] > 5 * max(counts[20], 1)


@pytest.mark.slow
@pytest.mark.ddp
@pytest.mark.parametrize("variant", ["whole", "parts"])
def test_ddp_keeps_codebooks_identical_and_stops_together(walker_dataset, tmp_path, variant):
    extra = ["parts"] if variant == "parts" else []
    # The whole tokenizer through Lightning's own launcher (the script starts rank 1 itself), as
    # `mmm train stage1 trainer.devices=2` does; the other DDP tests start both ranks forked.
    launch = "subprocess" if variant == "whole" else "forked"
    r0, r1 = run_ddp_worker(
        "stage1_ddp.py", walker_dataset, tmp_path, *extra, out_dir=tmp_path, launch=launch
    )
    assert r0["first_batch_sum"] != r1["first_batch_sum"]  # the ranks trained on different data
    assert r0["codebooks"] == (2 if variant == "parts" else 1)
    for key in ("codebook", "ema_sum", "ema_count", "window_usage", "weights"):
        assert torch.equal(r0[key], r1[key]), key
    assert r0["total_reset"] == r1["total_reset"] > 0
    # The monitor fired on rank 0 only (its threshold), yet both stopped at the same step.
    assert r0["global_step"] == r1["global_step"] == 24


@pytest.mark.slow
@pytest.mark.ddp
def test_ddp_decoder_refinement_freezes_the_same_codebook_on_both_ranks(walker_dataset, tmp_path):
    r0, r1 = run_ddp_worker("stage1_ddp.py", walker_dataset, tmp_path, "refine", out_dir=tmp_path)
    start = torch.load(tmp_path / "rank0-refine-start.pt", weights_only=True)
    assert r0["global_step"] == r1["global_step"] == 40
    assert r0["at_start"] and r1["at_start"]  # both ranks switched to clip-start windows
    for key, value in r0["tokenizer"].items():
        assert torch.equal(value, r1["tokenizer"][key]), key  # the ranks agree on every weight and buffer
        if "decoder" not in key.split("."):
            assert torch.equal(value, start[key]), key  # frozen from step 20 on
    decoder = [k for k in r0["tokenizer"] if k.startswith("decoder.")]
    assert sum(not torch.equal(r0["tokenizer"][k], start[k]) for k in decoder) > 10


def _stage1_overrides(root, out, steps, **extra):
    items = {
        "data.root": root,
        "data.synthesize": "null",
        "data.batch_size": 8,
        "model.tokenizer.width": 32,
        "model.tokenizer.num_codes": 64,
        "trainer.max_steps": steps,
        "trainer.val_check_interval": 5,
        "trainer.enable_progress_bar": "false",
        "optim.warmup_steps": 5,
        "refine.steps": 0,  # the resume test stops a run at 10 of 20 steps: no refinement to split
        "callbacks.reset_every_n_steps": 3,
        "callbacks.preview_clips": 2,
        "output_dir": out / "runs",
        "logger.tracking_uri": f"sqlite:///{out}/mlflow.db",
        "logger.artifact_root": out / "artifacts",
    }
    items.update(extra)
    return [f"{k}={v}" for k, v in items.items()]


@pytest.mark.slow
def test_resume_continues_the_run_and_matches_an_uninterrupted_one(walker_dataset, tmp_path):
    straight = train_stage1(load_stage1_config(_stage1_overrides(walker_dataset, tmp_path / "a", 20)))
    first = train_stage1(load_stage1_config(_stage1_overrides(walker_dataset, tmp_path / "b", 10)))
    resumed = train_stage1(
        load_stage1_config(_stage1_overrides(walker_dataset, tmp_path / "b", 20)), resume="last"
    )
    assert resumed.run_id == first.run_id and resumed.checkpoint_dir == first.checkpoint_dir

    def state(path):
        return torch.load(path, map_location="cpu", weights_only=True)  # checkpoints load safely

    a, b = state(straight.last_checkpoint), state(resumed.last_checkpoint)
    assert a["global_step"] == b["global_step"] == 20
    for key, value in a["state_dict"].items():
        assert torch.equal(value, b["state_dict"][key]), key
    assert a["state_dict"]["tokenizer.quantizer.codebook"].shape == (64, 32)

    client = MlflowClient(f"sqlite:///{tmp_path / 'b'}/mlflow.db")
    runs = client.search_runs([client.get_experiment_by_name("mmm-stage1").experiment_id])
    assert len(runs) == 1
    steps = [m.step for m in client.get_metric_history(first.run_id, "train/loss")]
    assert max(steps) >= 19 and min(steps) <= 10  # one run holds both halves
    assert client.get_run(first.run_id).data.params["model.tokenizer.num_codes"] == "64"
    artifacts = {f.path for f in client.list_artifacts(first.run_id)}
    assert {"checkpoints", "previews", "codebook", "config.yaml"} <= artifacts
    previews = [f.path for f in client.list_artifacts(first.run_id, "previews")]
    assert len(previews) == 4 and all(p.endswith(".gif") for p in previews)  # validations at 5, 10, 15, 20
    assert {f.path for f in client.list_artifacts(first.run_id, "checkpoints")} == {
        "checkpoints/best.ckpt",
        "checkpoints/last.ckpt",
    }
    history = client.get_metric_history(first.run_id, "val/mpjpe_root_aligned_mm")
    assert len(history) == 4 and all(np.isfinite(m.value) for m in history)
