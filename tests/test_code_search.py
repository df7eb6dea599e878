"""The code search (mmm.tokenizer.search): which codes it tries, that it keeps the best of them,
and where the package tokenizes with it."""

import itertools

import numpy as np
import pytest
import torch

from mmm.checkpoints import FINGERPRINT_KEY
from mmm.evaluation.run import reconstruction_metrics
from mmm.fingerprint import tensors_fingerprint
from mmm.motion.features import recover_from_ric
from mmm.tokenizer.load import load_tokenizer_checkpoint
from mmm.tokenizer.module import TokenizerModule
from mmm.tokenizer.network import TokenizerConfig
from mmm.tokenizer.quantizer import EMAQuantizer
from mmm.tokenizer.search import CodeSearchConfig, _joint_error, search_codes


def tokenizer(part_aware=False, candidates=4, sweeps=1, seed=0):
    """A tiny tokenizer with random weights, its codebook seeded from latents of random motion."""
    torch.manual_seed(seed)
    mean, std = torch.randn(263) * 0.1, torch.rand(263) * 0.5 + 0.5
    module = TokenizerModule(
        263,
        TokenizerConfig(width=16, num_codes=32, code_dim=8, part_aware=part_aware),
        {},
        {},
        mean=mean,
        std=std,
        encode={"candidates": candidates, "sweeps": sweeps},
    )
    module.train()
    module.tokenizer(torch.randn(4, 64, 263))
    return module.eval()


def motion(batch=3, frames=32, seed=1):
    """Normalized features (B, T, 263) of a smooth random motion (a random walk over frames)."""
    g = torch.Generator().manual_seed(seed)
    return torch.randn(batch, frames, 263, generator=g).cumsum(1) * 0.1


def error(module, indices, x):
    return _joint_error(module.joints(module.tokenizer.decode(indices)), module.joints(x))


def test_the_config_refuses_what_is_not_a_count_and_names_the_key():
    assert CodeSearchConfig().label == "search4x1" and CodeSearchConfig(1, 3).label == "nearest"
    for bad in ({"candidates": 0}, {"sweeps": -1}, {"candidates": 2.5}, {"candidates": True}):
        with pytest.raises(ValueError, match=f"encode.{next(iter(bad))}="):
            CodeSearchConfig(**bad)


def test_the_precision_is_checked_resolved_for_this_machine_and_names_token_caches(monkeypatch):
    import mmm.tokenizer.search as search

    with pytest.raises(ValueError, match="encode.precision='fp16'"):
        CodeSearchConfig(precision="fp16")
    assert CodeSearchConfig(precision="bf16").label == "search4x1-bf16"
    assert CodeSearchConfig(1, precision="bf16").label == "nearest"
    for fast, expected in ((True, "bf16"), (False, "fp32")):
        monkeypatch.setattr(search, "has_fast_bf16", lambda fast=fast: fast)
        assert CodeSearchConfig(precision="auto").resolved().precision == expected
        # The module searches with the resolved setting and keeps `auto` in its checkpoint.
        module = TokenizerModule(
            263, TokenizerConfig(width=16, num_codes=32, code_dim=8), {}, {}, encode={"precision": "auto"}
        )
        assert module.encode_cfg.precision == expected and module.hparams["encode"]["precision"] == "auto"
        assert module.encode_cfg.label == ("search4x1-bf16" if fast else "search4x1")


def test_the_choice_of_code_stays_float32_under_a_bfloat16_autocast():
    # Latent 1.0006 lies nearer code 1.001 than code 1.0; a bfloat16 matmul (8 bits of mantissa)
    # rounds both products to 1.0, and the distances' float32 norms then favour code 0.
    q = EMAQuantizer(num_codes=2, code_dim=1)
    q.codebook.copy_(torch.tensor([[1.0], [1.001]]))
    z = torch.tensor([[[1.0006]]])  # (B=1, C=1, T'=1)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert q.quantize(z).item() == 1 and q.nearest_codes(z, 2)[0, 0].tolist() == [1, 0]


def test_the_bfloat16_search_decodes_in_bfloat16_and_keeps_a_code_as_good():
    module = tokenizer(candidates=4)
    x = motion(batch=3, frames=32)
    dtypes = []
    hook = module.tokenizer.decoder.net[0].register_forward_hook(lambda m, i, o: dtypes.append(o.dtype))
    fp32 = search_codes(module.tokenizer, x, module.joints, CodeSearchConfig(precision="fp32"))
    assert set(dtypes) == {torch.float32}
    dtypes.clear()
    bf16 = search_codes(module.tokenizer, x, module.joints, CodeSearchConfig(precision="bf16"))
    hook.remove()
    assert set(dtypes) == {torch.bfloat16} and len(dtypes) == 1 + x.shape[1] // 4
    # Scored in float32, the bfloat16 choice is within rounding of the float32 one, and better
    # than the nearest codes (which both searches start from).
    nearest = error(module, module.tokenizer.encode(x), x)
    assert torch.all(error(module, bf16, x) <= error(module, fp32, x) * 1.02)
    assert torch.all(error(module, bf16, x) < nearest)


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_decoding_only_the_features_the_joints_read_gives_them_and_the_codes_to_the_bit(precision):
    module = tokenizer(candidates=4, seed=5)
    x = motion(batch=3, frames=40, seed=6)
    n = module.joint_features
    assert n == 67  # the root (4) and 21 joint positions (63) of the 263
    codes = module.tokenizer.encode(x)
    autocast = torch.autocast("cpu", dtype=torch.bfloat16, enabled=precision == "bf16")
    with autocast:
        full, first = module.tokenizer.decode(codes), module.tokenizer.decode(codes, n)
    assert first.shape == (3, 40, n) and first.dtype == torch.float32
    assert torch.equal(first, full[..., :n])
    assert torch.equal(module.joints(first), module.joints(full))
    cfg = CodeSearchConfig(candidates=4, precision=precision)
    whole = search_codes(module.tokenizer, x, module.joints, cfg)  # decodes all 263 features
    assert torch.equal(search_codes(module.tokenizer, x, module.joints, cfg, n), whole)
    with pytest.raises(ValueError, match="width 66 do not fit 22 joints"):
        module.joints(first[..., :66])


def test_the_part_aware_decoder_gives_the_first_features_of_its_merged_parts():
    module = tokenizer(part_aware=True)
    codes = module.tokenizer.encode(motion(batch=2, frames=16))
    assert torch.equal(module.tokenizer.decode(codes, 67), module.tokenizer.decode(codes)[..., :67])
    assert module.tokenizer.decode(codes, 67).shape == (2, 16, 67)


def test_nearest_codes_are_in_order_of_distance_and_start_with_the_quantized_one():
    q = EMAQuantizer(num_codes=5, code_dim=2)
    q.codebook.copy_(torch.tensor([[0.0, 0.0], [1.0, 0.0], [3.0, 0.0], [0.0, 2.5], [-0.4, 0.0]]))
    z = torch.tensor([[[0.9, 2.9], [0.1, 0.0]]])  # (B=1, C=2, T'=2): latents (0.9, 0.1) and (2.9, 0)
    codes = q.nearest_codes(z, 3)
    assert codes.shape == (1, 2, 3)
    assert codes[0, 0].tolist() == [1, 0, 4]  # distances 0.02, 0.82, 1.70
    assert codes[0, 1].tolist() == [2, 1, 0]  # 0.01, 3.61, 8.41
    assert torch.equal(codes[..., 0], q.quantize(z))
    assert q.nearest_codes(z, 99).shape == (1, 2, 5)  # at most the whole codebook


def test_one_candidate_is_the_nearest_code():
    module = tokenizer(candidates=1)
    x = motion()
    assert torch.equal(module.encode(x), module.tokenizer.encode(x))


def test_on_one_position_the_search_keeps_the_best_of_its_candidates():
    module = tokenizer(candidates=5)
    x = motion(batch=4, frames=4)  # one code per clip: the greedy pass is exhaustive
    candidates = module.tokenizer.candidate_codes(x, 5)  # (B, 1, 5)
    picked = module.encode(x)
    scores = torch.stack([error(module, candidates[:, :, k], x) for k in range(5)], dim=1)  # (B, 5)
    assert torch.equal(picked[:, 0], candidates[torch.arange(4), 0, scores.argmin(1)])
    assert (picked != candidates[..., 0]).any()  # the nearest code is not always the best decoded one


def test_on_two_positions_two_sweeps_find_what_brute_force_finds_or_no_worse():
    module = tokenizer(candidates=3, sweeps=2)
    x = motion(batch=6, frames=8)
    candidates = module.tokenizer.candidate_codes(x, 3)  # (B, 2, 3)
    picked = module.encode(x)
    rows = torch.arange(6)
    best = (
        torch.stack(
            [
                error(module, torch.stack((candidates[rows, 0, a], candidates[rows, 1, b]), dim=1), x)
                for a, b in itertools.product(range(3), range(3))
            ],
            dim=1,
        )
        .min(1)
        .values
    )
    found = error(module, picked, x)
    nearest = error(module, candidates[..., 0], x)
    assert (found <= nearest + 1e-6).all() and (found < nearest - 1e-6).any()
    # Greedy coordinate descent can stop short of the optimum, but not above the nearest codes.
    assert (found >= best - 1e-6).all() and (found <= best + 1e-6).float().mean() >= 0.5


@pytest.mark.parametrize("part_aware", [False, True])
def test_the_searched_codes_are_candidates_and_decode_no_worse_than_the_nearest(part_aware):
    module = tokenizer(part_aware=part_aware, candidates=3)
    x = motion(batch=3, frames=24)
    nearest = module.tokenizer.encode(x)
    picked = module.encode(x)
    assert picked.shape == nearest.shape == ((3, 6, 2) if part_aware else (3, 6))
    candidates = module.tokenizer.candidate_codes(x, 3)
    if not part_aware:
        candidates = candidates.unsqueeze(2)
    flat = picked if part_aware else picked.unsqueeze(-1)
    assert (flat[..., None] == candidates).any(-1).all()
    assert (error(module, picked, x) <= error(module, nearest, x) + 1e-6).all()
    assert not torch.equal(picked, nearest)


def test_the_search_decodes_once_per_position_on_the_other_candidates_copies_of_the_batch():
    module = tokenizer(candidates=3)
    x = motion(batch=2, frames=16)
    joints_of = []

    def joints(features):
        joints_of.append(features.shape[0])
        return module.joints(features)

    search_codes(module.tokenizer, x, joints, CodeSearchConfig(candidates=3))
    # the motion, the nearest codes' decoding, then one call per position on 2 copies of the batch:
    # the code in place is not decoded again
    assert joints_of == [2, 2] + [4] * 4


@pytest.mark.parametrize("sweeps", [1, 2])
def test_the_search_picks_what_scoring_every_candidate_in_turn_picks(sweeps):
    module = tokenizer(candidates=4, seed=3)
    x = motion(batch=3, frames=20, seed=4)
    candidates = module.tokenizer.candidate_codes(x, 4)  # (B, 5, 4)
    chosen = candidates[..., 0].clone()
    for _ in range(sweeps):  # greedy coordinate descent, each row and candidate decoded alone
        for row in range(3):
            for t in range(5):
                for code in candidates[row, t]:
                    trial = chosen[row : row + 1].clone()
                    trial[0, t] = code
                    one = x[row : row + 1]
                    if error(module, trial, one) < error(module, chosen[row : row + 1], one) - 1e-6:
                        chosen[row] = trial[0]
    picked = search_codes(module.tokenizer, x, module.joints, CodeSearchConfig(candidates=4, sweeps=sweeps))
    assert torch.equal(picked, chosen)
    assert not torch.equal(picked, candidates[..., 0])


def test_the_setting_lives_in_the_checkpoint_and_old_checkpoints_get_the_default(tmp_path):
    module = tokenizer(candidates=3, sweeps=2)
    assert module.hparams["encode"] == {"candidates": 3, "sweeps": 2, "precision": "fp32"}
    path = tmp_path / "tok.ckpt"

    def save(hparams):
        state = module.state_dict()
        torch.save(
            {"state_dict": state, "hyper_parameters": hparams, FINGERPRINT_KEY: tensors_fingerprint(state)},
            path,
        )

    save(dict(module.hparams))
    assert load_tokenizer_checkpoint(path).encode_cfg == CodeSearchConfig(3, 2)
    old = dict(module.hparams)
    del old["encode"]
    save(old)
    assert load_tokenizer_checkpoint(path).encode_cfg == CodeSearchConfig()


def test_reconstruction_metrics_report_the_search_and_the_nearest_codes():
    module = tokenizer(candidates=4)
    mean, std = module.mean.numpy(), module.std.numpy()
    clips = {
        f"{i:03d}": (motion(batch=1, frames=20 + 4 * i, seed=i)[0].numpy() * std + mean) for i in range(3)
    }
    result = reconstruction_metrics(module, None, clips)
    assert result["encoding"] == "search4x1" and result["clips"] == 3
    searched = result["mpjpe_global_mm"] + result["mpjpe_root_aligned_mm"]
    nearest = result["mpjpe_global_mm_nearest"] + result["mpjpe_root_aligned_mm_nearest"]
    assert searched < nearest
    # By hand: the nearest codes' global error of the clips, frame-weighted, in mm.
    total, frames = 0.0, 0
    for features in clips.values():
        x = torch.from_numpy(features.astype(np.float32))[None]
        rec = module.tokenizer.decode(module.tokenizer.encode((x - module.mean) / module.std)) * module.std
        j, jr = recover_from_ric(x), recover_from_ric(rec + module.mean)
        total += float((j - jr).norm(dim=-1).mean(-1).sum()) * module.skeleton.unit_scale * 1000
        frames += x.shape[1]
    assert result["mpjpe_global_mm_nearest"] == pytest.approx(total / frames, rel=1e-4)
    module.encode_cfg = CodeSearchConfig(candidates=1)
    plain = reconstruction_metrics(module, None, clips)
    assert plain["encoding"] == "nearest" and "mpjpe_global_mm_nearest" not in plain
    assert plain["mpjpe_global_mm"] == pytest.approx(result["mpjpe_global_mm_nearest"], rel=1e-5)


def test_text_to_motion_encodes_each_source_once_and_gives_the_codes_of_encoding_it_alone(monkeypatch):
    from mmm.generation.model import TextToMotion
    from mmm.transformer.network import MaskedMotionTransformer, TransformerConfig
    from tests.test_generation import FakeText

    module = tokenizer(candidates=3)
    transformer = MaskedMotionTransformer(
        module.tokenizer.codebook.detach(), TransformerConfig(embed_dim=32, num_heads=4, num_layers=2), 6, 5
    )
    model = TextToMotion(module, transformer.eval(), FakeText(), {"reference": "test"})
    mean, std = module.mean.numpy(), module.std.numpy()
    a, b = (motion(batch=1, frames=n, seed=n)[0].numpy() * std + mean for n in (22, 16))
    alone = [model.encode_motion(a), model.encode_motion(b)]
    assert alone[0].shape == (5,) and alone[1].shape == (4,)  # 22 frames: the usable 20
    calls = []
    encode = module.encode
    monkeypatch.setattr(module, "encode", lambda x: calls.append(x.shape) or encode(x))
    again = model.encode_motions([b, a, b])
    assert calls == []  # both seen before: no tokenizer call
    assert [c.tolist() for c in again] == [alone[1].tolist(), alone[0].tolist(), alone[1].tolist()]
    again[0][:] = -1  # a copy: the memo is untouched
    c = a + 0.01
    assert model.encode_motion(b).tolist() == alone[1].tolist()
    model.encode_motions([c, c])
    assert calls == [(1, 20, 263)]  # new content, given twice: encoded once
