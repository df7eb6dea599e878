"""Inference precision (issue 16): fp32 | bf16 | int8 decoding passes, never written back."""

import pytest
import torch

from mmm.cli.app import build_parser
from mmm.device import check_device
from mmm.generation.model import TextToMotion
from mmm.generation.precision import Int8Linear, default_precision, inference_copy
from mmm.generation.sampler import frames_to_codes, sample_tokens
from mmm.generation.settings import PRECISIONS, SamplingConfig, check_precision
from mmm.optim import OptimConfig
from mmm.tokenizer.configs import TokenizerLossConfig
from mmm.tokenizer.module import TokenizerModule
from mmm.tokenizer.network import TokenizerConfig
from tests.test_decoding_speedups import K, text, tiny_transformer


class FakeText:
    name, identity, sentence_dim, word_dim, max_words = "fake", "fake-0", 6, 5, 8

    def encode(self, texts):
        return text(len(texts))


@pytest.fixture(scope="module")
def t2m():
    torch.manual_seed(0)
    tok = TokenizerModule(
        263, TokenizerConfig(width=16, num_codes=K, code_dim=8), OptimConfig(), TokenizerLossConfig()
    ).eval()
    transformer = tiny_transformer()
    transformer.codebook.copy_(tok.tokenizer.codebook[:, :8].detach())
    return TextToMotion(tok, transformer, FakeText(), {"reference": "test"})


def test_unknown_precision_names_the_choices(t2m):
    with pytest.raises(ValueError, match="precision must be one of fp32, bf16, int8, got 'fp16'"):
        check_precision("fp16")
    with pytest.raises(ValueError, match="fp32, bf16, int8"):
        t2m.precision = "fp16"
    with pytest.raises(ValueError, match="fp32, bf16, int8"):
        TextToMotion.load("nowhere.ckpt", precision="half")
    assert t2m.precision == default_precision("cpu") == "int8" and PRECISIONS == ("fp32", "bf16", "int8")
    assert default_precision("cuda") == "fp32"  # int8 is CPU-only; bf16 is slower at batch 1 on a GPU


def test_devices_this_machine_lacks_are_refused_by_name(monkeypatch, t2m):
    assert check_device("cpu") == torch.device("cpu")
    with pytest.raises(ValueError, match=r"device='banana' is not a device: use cpu, or cuda"):
        check_device("banana")
    with pytest.raises(ValueError, match=r"device='meta': this package runs on cpu, cuda or mps, not meta"):
        check_device("meta")
    # No GPU (as on CI), and a machine with one GPU asked for its second: named, with the fix.
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(
        ValueError, match=r"--device='cuda': no CUDA GPU is available here .*use --device=cpu"
    ):
        check_device("cuda", "--device")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    assert check_device("cuda:0") == torch.device("cuda", 0)
    with pytest.raises(
        ValueError, match=r"device='cuda:1': this machine has 1 CUDA GPU\(s\), cuda:0 to cuda:0"
    ):
        check_device("cuda:1")
    # A model is never half-built on a device that is not there.
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(ValueError, match="no CUDA GPU"):
        TextToMotion(t2m.tokenizer, t2m.transformer, FakeText(), {"reference": "test"}, device="cuda")


def test_inference_copies_never_touch_the_trained_weights():
    model = tiny_transformer()
    before = {k: v.clone() for k, v in model.state_dict().items()}
    copies = {p: inference_copy(model, p) for p in PRECISIONS}
    assert copies["fp32"] is model
    assert isinstance(copies["int8"].layers[0].mlp[0], Int8Linear)
    assert copies["bf16"].layers[0].mlp[0].weight.dtype == torch.bfloat16
    assert copies["int8"].codebook is model.codebook  # what is not converted is shared, not copied
    emb = text(2)
    codes = frames_to_codes(torch.tensor([120, 40]))
    for p in PRECISIONS:
        sample_tokens(copies[p], emb, codes, SamplingConfig(), generator=torch.Generator().manual_seed(0))
    after = model.state_dict()
    assert after.keys() == before.keys()
    assert all(torch.equal(before[k], after[k]) and after[k].dtype == before[k].dtype for k in before)
    assert all(p.dtype == torch.float32 and p.requires_grad for p in model.parameters())


def test_int8_linear_is_close_to_the_float_layer():
    torch.manual_seed(0)
    linear = torch.nn.Linear(64, 48)
    x = torch.randn(3, 7, 64)
    q = Int8Linear(linear)
    assert q.qweight_t.dtype == torch.int8 and q.qweight_t.shape == (64, 48)
    reference = linear(x)
    assert (q(x) - reference).abs().max() < 0.02 * reference.abs().max()


@pytest.mark.parametrize("precision", PRECISIONS)
def test_every_precision_generates_and_stays_close_to_fp32(t2m, precision):
    # Over 5 seeds: one code drawn otherwise changes the context of every later pass, so a single
    # seed's share swings (0.73-1.0 for bf16 on this model).
    t2m.precision = "fp32"
    reference = [t2m.generate(["a", "b"], frames=[120, 60], seed=seed) for seed in range(5)]
    t2m.precision = precision
    try:
        outs = [t2m.generate(["a", "b"], frames=[120, 60], seed=seed) for seed in range(5)]
        assert t2m.inference_transformer.__class__ is type(t2m.transformer)
        if precision != "fp32":
            assert t2m.inference_transformer is not t2m.transformer
            assert t2m.inference_transformer is t2m.inference_transformer  # built once
    finally:
        t2m.precision = "fp32"
    assert [f.shape for f in outs[0].features] == [(120, 263), (60, 263)]
    pairs = [(a, b) for out, ref in zip(outs, reference) for a, b in zip(out.codes, ref.codes)]
    same = sum(int((a == b).sum()) for a, b in pairs) / sum(len(a) for a, _ in pairs)
    assert same == 1.0 if precision == "fp32" else same > 0.85


def test_cli_and_evaluate_take_a_precision():
    parser = build_parser()
    for command in (["generate", "--text", "x"], ["generate-long", "--text", "x"]):
        args = parser.parse_args([*command, "--out", "o", "--precision", "int8"])
        assert args.precision == "int8"
    with pytest.raises(SystemExit):
        parser.parse_args(["generate", "--text", "x", "--out", "o", "--precision", "fp16"])
    from mmm.evaluation.configs import load_evaluate_config

    assert load_evaluate_config(["precision=bf16"]).precision == "bf16"
    assert load_evaluate_config([]).precision is None


# -- training precision -----------------------------------------------------------------------------
@pytest.mark.parametrize(
    "precision, has_bf16, warned",
    [
        ("bf16-mixed", False, True),
        ("bf16-mixed", True, False),
        ("bf16-mixed", None, False),
        ("32-true", False, False),
    ],
)
def test_bf16_training_on_a_cpu_without_bf16_units_warns_with_the_fix(
    tmp_path, monkeypatch, caplog, precision, has_bf16, warned
):
    from mmm.training import common
    from mmm.training.configs import TrainerConfig

    monkeypatch.setattr(common, "cpu_has_bf16_matmul", lambda: has_bf16)
    cfg = TrainerConfig(max_steps=1, enable_progress_bar=False, precision=precision)
    with caplog.at_level("WARNING", logger=common.__name__):
        trainer = common.build_trainer(cfg, [], None, str(tmp_path))
    assert trainer.precision == precision
    messages = [r.getMessage() for r in caplog.records if r.name == common.__name__]
    assert messages == (
        [
            "trainer.precision=bf16-mixed on a CPU without bfloat16 kernels (AVX-512 or newer) "
            "trains slower than float32; set trainer.precision=32-true (or auto)"
        ]
        if warned
        else []
    )


@pytest.mark.parametrize(
    "accelerator, has_bf16, cuda_bf16, expected",
    [
        ("cpu", True, None, "bf16-mixed"),  # AVX-512 BF16 / AMX
        ("cpu", False, None, "32-true"),  # AVX2 only: the autocast would emulate every matmul
        ("cpu", None, None, "32-true"),  # this build of torch cannot tell: the safe choice
        ("gpu", False, True, "bf16-mixed"),  # the GPU's own support decides, not the host CPU's
        ("gpu", True, False, "32-true"),
    ],
)
def test_auto_precision_trains_in_bf16_only_where_the_device_has_bf16_kernels(
    tmp_path, monkeypatch, caplog, accelerator, has_bf16, cuda_bf16, expected
):
    from mmm.training import common
    from mmm.training.configs import TrainerConfig

    monkeypatch.setattr(common, "cpu_has_bf16_matmul", lambda: has_bf16)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: cuda_bf16 is not None)
    monkeypatch.setattr(torch.cuda, "is_bf16_supported", lambda *a, **k: bool(cuda_bf16))
    assert common.training_precision("auto", accelerator) == expected
    assert common.training_precision("16-mixed", accelerator) == "16-mixed"  # other names are kept
    if accelerator == "cpu":
        cfg = TrainerConfig(max_steps=1, enable_progress_bar=False, precision="auto")
        with caplog.at_level("INFO", logger=common.__name__):
            trainer = common.build_trainer(cfg, [], None, str(tmp_path))
        assert trainer.precision == expected
        messages = [r.getMessage() for r in caplog.records if r.name == common.__name__]
        assert messages == [f"trainer.precision=auto: {expected} (bfloat16 kernels on this cpu: {has_bf16})"]


def test_cpu_bf16_autocast_runs_attention_in_float32_with_the_same_result(monkeypatch):
    """Under a CPU bfloat16 autocast (training with bf16-mixed, bf16 decoding) the attention kernel
    gets float32 inputs: PyTorch's bfloat16 CPU kernel is several times slower on these short
    sequences. The layer still returns bfloat16, and its output and gradients match float32's."""
    import torch.nn.functional as F

    from mmm.transformer import network

    torch.manual_seed(0)
    attention = network.Attention(32, 4, dropout=0.0)
    x, context = torch.randn(3, 9, 32), torch.randn(3, 5, 32)
    mask = torch.ones(3, 5, dtype=torch.bool)
    mask[0, 3:] = False
    kernel_dtypes, kernel = [], F.scaled_dot_product_attention

    def recording(q, k, v, **kwargs):
        kernel_dtypes.append({q.dtype, k.dtype, v.dtype})
        return kernel(q, k, v, **kwargs)

    monkeypatch.setattr(network.F, "scaled_dot_product_attention", recording)

    def run(bf16: bool):
        attention.zero_grad()
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            y = attention(x, context, mask)
        y.float().square().sum().backward()
        return y, attention.kv.weight.grad.clone()

    y32, grad32 = run(bf16=False)
    y16, grad16 = run(bf16=True)
    assert kernel_dtypes == [{torch.float32}, {torch.float32}]
    assert y32.dtype == torch.float32 and y16.dtype == torch.bfloat16
    scale = y32.abs().max()
    assert (y16.float() - y32).abs().max() < 0.03 * scale
    assert (grad16 - grad32).abs().max() < 0.05 * grad32.abs().max()
    # Masked context positions stay masked on the float32 path: the padding cannot move the output.
    context2 = context.clone()
    context2[0, 3:] = 100.0
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        assert torch.equal(attention(x, context2, mask)[0], attention(x, context, mask)[0])
