"""Less work per decoding pass (issue 16): the cached loop draws the same codes as the plain one."""

import pytest
import torch

from mmm.generation.sampler import SamplingConfig, frames_to_codes, sample_tokens
from mmm.text import TextEmbedding
from mmm.tokenizer.network import MotionTokenizer, TokenizerConfig
from mmm.transformer.network import MaskedMotionTransformer, TransformerConfig

K = 64


def tiny_transformer(variant="fixed", cross=1, condition=False):
    torch.manual_seed(0)
    codebook = torch.randn(K, 8)
    model = MaskedMotionTransformer(
        codebook,
        TransformerConfig(
            embed_dim=32, num_heads=4, num_layers=3, num_cross_layers=cross, dropout=0.0, variant=variant
        ),
        6,
        5,
        condition_codebook=torch.randn(16, 4) if condition else None,
    )
    with torch.no_grad():  # larger weights than the init's, so the logits are far from uniform
        for p in model.parameters():
            p.add_(torch.randn_like(p) * 0.2)
    return model.eval()


def text(batch, words=7):
    g = torch.Generator().manual_seed(1)
    mask = torch.ones(batch, words, dtype=torch.bool)
    for i in range(batch):
        mask[i, 2 + i % (words - 2) :] = False
    return TextEmbedding(
        torch.randn(batch, 6, generator=g), torch.randn(batch, words, 5, generator=g), mask, 0
    )


def both(model, frames, cfg, **kwargs):
    codes = frames_to_codes(torch.tensor(frames))
    emb = text(len(frames))
    out = []
    for reference in (True, False):
        g = torch.Generator().manual_seed(7)
        out.append(sample_tokens(model, emb, codes, cfg, generator=g, reference=reference, **kwargs))
    return out


CASES = [
    ("fixed", 1, {}),
    ("fixed", 2, {"temperature": 0.0}),
    ("fixed", 1, {"guidance_scale": 3.0, "top_k": 0.5}),
    ("fixed", 0, {"top_p": 0.9, "schedule": "linear", "max_iterations": 7}),
    ("released", 1, {"dynamic_iterations": False}),
    ("released", 0, {}),
]


@pytest.mark.parametrize("variant, cross, settings", CASES)
def test_cached_decoding_draws_the_same_codes(variant, cross, settings):
    model = tiny_transformer(variant, cross)
    cfg = SamplingConfig(**settings)
    frames = [196, 40, 120, 81, 4, 9]  # mixed lengths: rows finish at different passes
    ref, fast = both(model, frames, cfg)
    assert torch.equal(ref.tokens, fast.tokens)
    assert torch.equal(ref.iterations, fast.iterations) and ref.forward_passes == fast.forward_passes
    ref1, fast1 = both(model, [196], cfg)  # batch 1, every row running every pass
    assert torch.equal(ref1.tokens, fast1.tokens)


def test_cached_decoding_with_edits_no_text_and_conditions():
    model = tiny_transformer()
    frames = [160, 64, 100]
    L = int(frames_to_codes(torch.tensor(max(frames))))
    keep_tokens = torch.randint(0, K, (3, L), generator=torch.Generator().manual_seed(2))
    keep_mask = torch.zeros(3, L, dtype=torch.bool)
    keep_mask[0, :10] = True
    keep_mask[1, 4:8] = True
    no_text = torch.tensor([False, True, False])
    for cfg in (SamplingConfig(), SamplingConfig(guidance_scale=2.5)):
        ref, fast = both(model, frames, cfg, keep_tokens=keep_tokens, keep_mask=keep_mask, no_text=no_text)
        assert torch.equal(ref.tokens, fast.tokens)
        assert torch.equal(fast.tokens[0, :10], keep_tokens[0, :10])
    parts = tiny_transformer(condition=True)
    condition = torch.randint(0, 19, (3, L), generator=torch.Generator().manual_seed(3))
    ref, fast = both(parts, frames, SamplingConfig(guidance_scale=2.0), condition=condition)
    assert torch.equal(ref.tokens, fast.tokens)


def test_cached_decoding_traces_like_the_reference():
    model = tiny_transformer()
    ref, fast = both(model, [120, 40], SamplingConfig(), trace=True)
    for a, b in zip(ref.trace.confidence, fast.trace.confidence):
        assert torch.equal(a.isnan(), b.isnan()) and torch.allclose(a.nan_to_num(), b.nan_to_num())
    assert all(torch.equal(a, b) for a, b in zip(ref.trace.masked, fast.trace.masked))


def test_logits_of_cached_forward_equal_forward():
    model = tiny_transformer()
    emb = text(3)
    tokens = torch.randint(0, K + 3, (3, 12), generator=torch.Generator().manual_seed(4))
    tokens[:, -1] = model.end_id
    drop = torch.tensor([False, True, False])
    full = model(tokens, emb.sentence, emb.words, emb.word_mask, drop)
    context = model.text_context(emb.sentence, emb.words, emb.word_mask, drop)
    assert torch.allclose(model.forward_cached(tokens, context), full, atol=1e-6)
    rows = torch.tensor([0, 5, 13, 35])
    assert torch.allclose(
        model.forward_cached(tokens, context, head_rows=rows), full.flatten(0, 1)[rows], atol=1e-6
    )


def test_mixed_length_batch_decodes_in_one_call_like_each_alone():
    torch.manual_seed(0)
    tokenizer = MotionTokenizer(263, TokenizerConfig(width=32, num_codes=K, code_dim=8)).eval()
    lengths = [49, 10, 31, 1]
    codes = torch.randint(0, K, (4, 49), generator=torch.Generator().manual_seed(5))
    together = tokenizer.decode_lengths(codes, torch.tensor(lengths))
    for i, n in enumerate(lengths):
        alone = tokenizer.decode(codes[i : i + 1, :n])[0]
        assert torch.allclose(together[i, : 4 * n], alone, atol=1e-5)
        assert not together[i, 4 * n :].any()
