"""The lower/upper body split and the part-aware tokenizer: split/merge, the two codebooks in
training (metrics, reset, collapse), checkpoints."""

import lightning as L
import numpy as np
import pytest
import torch
from mlflow.tracking import MlflowClient

from mmm.callbacks.codebook import CodebookCollapseError, CodebookReset, CollapseMonitor
from mmm.motion.parts import LOWER_JOINTS, UPPER_JOINTS, merge_parts, part_indices, split_parts
from mmm.optim import OptimConfig
from mmm.tokenizer.configs import TokenizerLossConfig
from mmm.tokenizer.load import load_tokenizer_checkpoint
from mmm.tokenizer.module import TokenizerModule
from mmm.tokenizer.network import MotionTokenizer, TokenizerConfig
from mmm.tokenizer.parts import PartAwareTokenizer

TINY = TokenizerConfig(width=16, num_codes=32, part_aware=True)


# -- the split -------------------------------------------------------------------------------------


def test_split_then_merge_is_the_identity_on_reference_data(reference_dir):
    path = reference_dir / "humanml3d" / "new_joint_vecs" / "012314.npy"
    if not path.exists():
        pytest.skip(f"{path} not available")
    features = np.load(path)
    lower, upper = split_parts(features)
    assert lower.shape == (len(features), 107) and upper.shape == (len(features), 156)
    assert np.array_equal(merge_parts(lower, upper), features)
    as_tensor = torch.from_numpy(features)
    assert torch.equal(merge_parts(*split_parts(as_tensor)), as_tensor)


@pytest.mark.parametrize("shape", [(263,), (7, 263), (2, 3, 263)])
def test_split_then_merge_is_the_identity_on_any_leading_shape(shape):
    x = np.random.default_rng(0).normal(size=shape)
    lower, upper = split_parts(x)
    assert lower.shape == shape[:-1] + (107,) and upper.shape == shape[:-1] + (156,)
    assert np.array_equal(merge_parts(lower, upper), x)
    t = torch.randn(shape, dtype=torch.float64, requires_grad=True)
    merged = merge_parts(*split_parts(t))
    assert torch.equal(merged, t)
    merged.sum().backward()  # the merge is a gather: gradients reach every feature once
    assert torch.equal(t.grad, torch.ones_like(t))


def test_index_sets_partition_the_features():
    lower, upper = part_indices()
    assert len(lower) == 107 and len(upper) == 156
    assert not set(lower) & set(upper) and sorted([*lower, *upper]) == list(range(263))
    assert list(lower) == sorted(lower) and list(upper) == sorted(upper)
    assert LOWER_JOINTS == (0, 1, 2, 4, 5, 7, 8, 10, 11) and len(UPPER_JOINTS) == 13
    assert {0, 1, 2, 3, 259, 260, 261, 262} <= set(lower)  # root features and foot contacts
    assert {193, 194, 195} <= set(lower)  # the pelvis velocity
    assert set(range(61, 67)) <= set(upper)  # the wrists' positions (joints 20 and 21)
    assert set(range(4, 7)) <= set(lower)  # the left hip's position (joint 1)


def test_wrong_widths_and_kit_are_refused():
    with pytest.raises(ValueError, match="263 values"):
        split_parts(np.zeros((4, 262)))
    with pytest.raises(ValueError, match="KIT-ML"):
        split_parts(torch.zeros(4, 251))
    with pytest.raises(ValueError, match="KIT-ML"):
        part_indices(21)
    with pytest.raises(ValueError, match="156 values"):
        merge_parts(np.zeros((4, 107)), np.zeros((4, 150)))
    with pytest.raises(ValueError, match="part_aware=false"):
        PartAwareTokenizer(251, TINY)


# -- the tokenizer ---------------------------------------------------------------------------------


def _trained_once(seed=0) -> PartAwareTokenizer:
    """A tiny part-aware tokenizer whose codebooks were seeded by one training batch, in eval mode."""
    torch.manual_seed(seed)
    tokenizer = PartAwareTokenizer(263, TINY)
    tokenizer.train()
    tokenizer(torch.randn(4, 32, 263))
    return tokenizer.eval()


@pytest.mark.slow
def test_part_aware_tokenizer_shapes():
    tokenizer = PartAwareTokenizer(263, TINY)
    tokenizer.train()
    out = tokenizer(torch.randn(2, 32, 263))
    assert out.reconstruction.shape == (2, 32, 263) and out.indices.shape == (2, 8, 2)
    assert set(out.perplexities) == {"lower", "upper"}
    assert torch.allclose(out.perplexity, (out.perplexities["lower"] + out.perplexities["upper"]) / 2)
    tokenizer.eval()
    codes = tokenizer.encode(torch.randn(3, 40, 263))
    assert codes.shape == (3, 10, 2) and codes.dtype == torch.long
    assert tokenizer.decode(codes).shape == (3, 40, 263)
    assert tokenizer.feature_dim == 263 and tokenizer.cfg is TINY
    assert tokenizer.part_aware and not tokenizer.lower.part_aware and not tokenizer.upper.part_aware
    assert tokenizer.quantizers == {"lower": tokenizer.lower.quantizer, "upper": tokenizer.upper.quantizer}
    assert (tokenizer.lower.feature_dim, tokenizer.upper.feature_dim) == (107, 156)
    plain = MotionTokenizer(263, TokenizerConfig(width=16, num_codes=32))
    assert plain.quantizers == {"": plain.quantizer}
    with pytest.raises(ValueError, match=r"\(B, T', 2\)"):
        tokenizer.decode(codes[..., 0])


@pytest.mark.slow
def test_decode_parts_combines_the_lower_body_of_one_motion_with_the_upper_of_another():
    tokenizer = _trained_once()
    a, b = torch.randn(2, 40, 263), torch.randn(2, 40, 263) + 1.0
    codes_a, codes_b = tokenizer.encode(a), tokenizer.encode(b)
    mixed = tokenizer.decode_parts(codes_a[..., 0], codes_b[..., 1])
    lower, upper = split_parts(mixed)
    assert torch.equal(lower, tokenizer.lower.decode(codes_a[..., 0]))
    assert torch.equal(upper, tokenizer.upper.decode(codes_b[..., 1]))
    assert torch.equal(tokenizer.decode(codes_a), tokenizer.decode_parts(codes_a[..., 0], codes_a[..., 1]))


# -- training --------------------------------------------------------------------------------------


@pytest.mark.slow
def test_stage1_trains_a_part_aware_tokenizer_with_metrics_per_codebook(walker_dataset, tmp_path):
    from tests.helpers import train_tiny_stage1

    result = train_tiny_stage1(
        walker_dataset,
        tmp_path,
        "model.tokenizer.part_aware=true",
        "trainer.log_every_n_steps=1",
        "callbacks.reset_every_n_steps=2",
        "callbacks.usage_plot=true",
    )
    client = MlflowClient(f"sqlite:///{tmp_path}/mlflow.db")
    logged = set(client.get_run(result.run_id).data.metrics)
    per_codebook = {
        f"{group}/{part}/{name}"
        for part in ("lower", "upper")
        for group, name in [
            ("codebook", "perplexity"),
            ("codebook", "used_since_reset_fraction"),
            ("codebook", "used_since_reset"),
            ("codebook", "codes_reset_total"),
            ("collapse", "window_active_fraction"),
            ("collapse", "perplexity_ratio"),
        ]
    }
    assert per_codebook | {"codebook/codes_reset_total", "val/mpjpe_root_aligned_mm"} <= logged
    assert "codebook/perplexity" not in logged  # no name that hides which codebook it is
    assert {"codebook/lower", "codebook/upper"} <= {
        f.path for f in client.list_artifacts(result.run_id, "codebook")
    }

    module = load_tokenizer_checkpoint(result.best_checkpoint)
    assert isinstance(module.tokenizer, PartAwareTokenizer)
    saved = torch.load(result.best_checkpoint, map_location="cpu", weights_only=True)
    assert saved["hyper_parameters"]["model"]["part_aware"] is True
    state = module.state_dict()
    assert state.keys() == saved["state_dict"].keys()
    assert all(torch.equal(value, saved["state_dict"][key]) for key, value in state.items())
    assert bool(module.quantizers["lower"].initialized) and bool(module.quantizers["upper"].initialized)
    with pytest.raises(TypeError, match="quantizers"):
        module.quantizer


def _module() -> TokenizerModule:
    return TokenizerModule(263, TINY, OptimConfig(warmup_steps=5), TokenizerLossConfig())


def _fit(module, callbacks, steps, frames=32):
    trainer = L.Trainer(
        max_steps=steps,
        callbacks=callbacks,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        limit_val_batches=0,
        accelerator="cpu",
        enable_model_summary=False,
        log_every_n_steps=1,  # every step's values in callback_metrics (they are logged steps)
    )
    data = torch.randn(64, frames, 263)
    trainer.fit(module, torch.utils.data.DataLoader(data, batch_size=16, shuffle=True))
    return trainer


class KillCodes(L.Callback):
    """Before the reset at `step`, mark codes 0..3 of every codebook as unused since the last
    reset (and every other code as used) and keep the codebooks as they were."""

    def __init__(self, step):
        self.step, self.before = step, {}

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        if trainer.global_step != self.step:
            return
        for name, q in pl_module.quantizers.items():
            q.window_usage.fill_(1.0)
            q.window_usage[:4] = 0.0
            self.before[name] = q.codebook.clone()


def test_codebook_reset_resets_the_dead_codes_of_both_codebooks():
    torch.manual_seed(0)
    module = _module()
    kill, reset = KillCodes(step=2), CodebookReset(every_n_steps=2)
    trainer = _fit(module, [kill, reset], steps=2)  # callbacks run in order: kill, then reset
    assert set(kill.before) == {"lower", "upper"} and reset.total_reset == 8
    for name, q in module.quantizers.items():
        changed = (q.codebook != kill.before[name]).any(dim=-1)
        assert changed[:4].all() and not changed[4:].any(), name
        assert q.window_usage.sum() == 0
        assert trainer.callback_metrics[f"codebook/{name}/codes_reset_total"] == 4
    assert trainer.callback_metrics["codebook/codes_reset_total"] == 8


class DegenerateEncoder(torch.nn.Module):
    """Every latent the same: all tokens fall into one code."""

    def forward(self, x):
        return torch.zeros(x.shape[0], TINY.code_dim, x.shape[2] // 4) + 0.0 * x.mean()


def test_collapse_of_the_upper_codebook_alone_is_detected_and_named():
    torch.manual_seed(0)
    module = _module()
    module.tokenizer.upper.encoder = DegenerateEncoder()
    monitor = CollapseMonitor(
        action="fail", warmup_steps=6, window_steps=3, min_active_fraction=0.1, patience=2
    )
    with pytest.raises(CodebookCollapseError, match="upper codebook: active codes 3.12%"):
        _fit(module, [monitor], steps=30)
    assert [e.codebook for e in monitor.events] == ["upper"]
    assert monitor.codebooks["lower"].active_fraction > 0.5 and monitor.codebooks[
        "upper"
    ].active_fraction == pytest.approx(1 / 32)

    # The state round-trips exactly (resume), per codebook.
    restored = CollapseMonitor()
    restored.load_state_dict(monitor.state_dict())
    assert restored.events == monitor.events and restored.codebooks.keys() == monitor.codebooks.keys()
    for name, health in monitor.codebooks.items():
        copy = restored.codebooks[name]
        assert torch.equal(copy.usage, health.usage)
        assert (copy.steps_in_window, copy.active_fraction, copy.perplexity, copy.peak, copy.strikes) == (
            health.steps_in_window,
            health.active_fraction,
            health.perplexity,
            health.peak,
            health.strikes,
        )


def test_collapse_monitor_resumes_from_a_single_codebook_state():
    """Checkpoints of plain runs written before the monitor followed several codebooks."""
    old = {
        "usage": torch.ones(8),
        "steps_in_window": 2,
        "active_fraction": 0.5,
        "perplexity": 3.0,
        "peak": 4.0,
        "strikes": 1,
        "events": [
            {
                "step": 5,
                "reason": "r",
                "active_fraction": 0.1,
                "perplexity": 1.0,
                "perplexity_peak": 2.0,
                "action": "warn",
            }
        ],
    }
    monitor = CollapseMonitor()
    monitor.load_state_dict(old)
    assert (
        list(monitor.codebooks) == [""]
        and monitor.codebooks[""].strikes == 1
        and monitor.active_fraction == 0.5
    )
    assert monitor.events[0].codebook == "" and monitor.events[0].describe() == "r"
