"""Decoding passes through torch.compile with static shapes (issue 16, item 3): length, word and
row buckets, the same codes as the uncompiled passes, the trained weights untouched."""

import pytest
import torch

from mmm.cli.app import build_parser
from mmm.generation.compiled import CompiledDecoding, length_buckets
from mmm.generation.precision import inference_copy
from mmm.generation.sampler import SamplingConfig, frames_to_codes, sample_tokens
from tests.test_decoding_speedups import K, text, tiny_transformer
from tests.test_precision import t2m  # noqa: F401 (the fixture)


def codes(model, frames, cfg, **kwargs):
    lengths = frames_to_codes(torch.tensor(frames))
    g = torch.Generator().manual_seed(7)
    return sample_tokens(model, text(len(frames)), lengths, cfg, generator=g, **kwargs).tokens


def test_buckets_are_few_and_cover_every_length():
    assert length_buckets(50) == (4, 8, 12, 16, 24, 32, 40, 48, 50)
    assert length_buckets(12) == (4, 8, 12) and length_buckets(14) == (4, 8, 12, 14)
    wrapped = CompiledDecoding(tiny_transformer(), backend="eager")
    assert [wrapped.bucket(n) for n in (1, 8, 9, 11, 17, 49, 50)] == [4, 8, 12, 12, 24, 50, 50]
    with pytest.raises(ValueError, match="51 tokens is longer than the model's 50"):
        wrapped.bucket(51)


@pytest.mark.parametrize(
    "variant, cross, settings",
    [
        ("fixed", 1, {}),
        ("fixed", 2, {"guidance_scale": 3.0, "top_k": 0.5}),
        ("released", 1, {"dynamic_iterations": False}),
    ],
)
def test_padded_passes_draw_the_codes_of_the_unpadded_ones(variant, cross, settings):
    """Dynamo's capture without a compiler (backend=eager): what the padding does, quickly."""
    model = tiny_transformer(variant, cross)
    wrapped = CompiledDecoding(model, backend="eager")
    cfg = SamplingConfig(**settings)
    # Mixed lengths: 3 of 6 rows padded to 8 rows, lengths padded to their buckets; words (7, some
    # masked) padded to 16.
    frames = [196, 40, 120, 81, 4, 9]
    assert torch.equal(codes(wrapped, frames, cfg), codes(model, frames, cfg))
    assert torch.equal(codes(wrapped, [196], cfg), codes(model, [196], cfg))


def test_padded_passes_with_edits_no_text_and_part_aware_conditions():
    model = tiny_transformer()
    wrapped = CompiledDecoding(model, backend="eager")
    frames = [160, 64, 100]
    L = int(frames_to_codes(torch.tensor(max(frames))))
    keep_tokens = torch.randint(0, K, (3, L), generator=torch.Generator().manual_seed(2))
    keep_mask = torch.zeros(3, L, dtype=torch.bool)
    keep_mask[0, :10] = True
    edits = {
        "keep_tokens": keep_tokens,
        "keep_mask": keep_mask,
        "no_text": torch.tensor([False, True, False]),
    }
    cfg = SamplingConfig(guidance_scale=2.5)
    assert torch.equal(codes(wrapped, frames, cfg, **edits), codes(model, frames, cfg, **edits))
    parts = tiny_transformer(condition=True)
    condition = torch.randint(0, 19, (3, L), generator=torch.Generator().manual_seed(3))
    wrapped_parts = CompiledDecoding(parts, backend="eager")
    assert torch.equal(
        codes(wrapped_parts, frames, cfg, condition=condition), codes(parts, frames, cfg, condition=condition)
    )


@pytest.mark.slow
def test_inductor_compiles_each_shape_once_and_draws_the_same_codes():
    model = tiny_transformer()
    wrapped = CompiledDecoding(model)  # inductor: real kernels, compiled on this CPU
    cfg = SamplingConfig()
    first = codes(wrapped, [196], cfg)
    graphs = torch._dynamo.utils.counters["stats"]["unique_graphs"]
    assert torch.equal(first, codes(model, [196], cfg))
    assert torch.equal(codes(wrapped, [193], cfg), codes(model, [193], cfg))  # the same 50-token shape
    assert torch.equal(codes(wrapped, [196], cfg), first)
    assert torch._dynamo.utils.counters["stats"]["unique_graphs"] == graphs  # nothing compiled again


def test_text_to_motion_compiles_an_inference_copy_and_keeps_the_weights(t2m):  # noqa: F811
    before = {k: v.clone() for k, v in t2m.transformer.state_dict().items()}
    t2m.precision = "fp32"
    reference = t2m.generate(["a", "b"], frames=[120, 60], seed=3)
    t2m.compiled = True
    try:
        wrapped = t2m.inference_transformer
        assert isinstance(wrapped, CompiledDecoding) and wrapped.mode == "default"
        assert wrapped.model is t2m.transformer and t2m.inference_transformer is wrapped  # built once
        wrapped._pass = torch.compile(wrapped._logits, dynamic=False, backend="eager")  # no compiler here
        out = t2m.generate(["a", "b"], frames=[120, 60], seed=3)
        t2m.precision = "int8"
        assert isinstance(t2m.inference_transformer.model, type(inference_copy(t2m.transformer, "int8")))
        assert t2m.inference_transformer.model is not t2m.transformer
    finally:
        t2m.compiled, t2m.precision = False, "fp32"
    assert t2m.inference_transformer is t2m.transformer
    t2m.precision = None  # back to the device's default
    assert all((a == b).all() for a, b in zip(out.codes, reference.codes))
    assert all(torch.equal(v, before[k]) for k, v in t2m.transformer.state_dict().items())
    args = build_parser().parse_args(["generate", "--text", "x", "--out", "o", "--compile"])
    assert args.compile is True


def test_the_served_bundle_compiles_when_its_model_config_says_so(monkeypatch):
    from types import SimpleNamespace

    from mmm.generation.model import TextToMotion
    from mmm.registry.bundle import TextToMotionPyfunc

    monkeypatch.setattr(
        TextToMotion,
        "from_files",
        classmethod(lambda cls, *a, **k: SimpleNamespace(part_aware=False, precision="fp32", compiled=False)),
    )

    def load(config):
        bundle = TextToMotionPyfunc()
        bundle.load_context(
            SimpleNamespace(model_config=config, artifacts={"transformer": "t", "tokenizer": "s"})
        )
        return bundle.model.compiled

    assert load({}) is False and load({"compile": True}) is True
    with pytest.raises(ValueError, match="model_config \"compile\" must be true or false, got 'yes'"):
        load({"compile": "yes"})
