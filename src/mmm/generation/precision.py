"""Inference precision of the stage-2 transformer: fp32 | bf16 | int8 (issue 16).

    fp32  the trained weights as they are (float32 throughout).
    bf16  torch.autocast(bfloat16) around every decoding pass, on CPU and GPU; the linear layers'
          weights are cast to bfloat16 once, in the inference copy, so autocast does not cast
          them again on every pass (LayerNorm, softmax and the residual stream stay float32,
          autocast's own rules).
    int8  the linear layers of the attention/MLP blocks and the output head hold int8 weights,
          symmetric per output row (torchao's `Int8Tensor.from_hp(..., PerRow())` computes them);
          activations are quantized per token on the fly (dynamic, symmetric) and multiplied with
          `torch._int_mm` (oneDNN, AVX-512 VNNI on CPU), the result scaled back to float32.
          torchao's own eager int8 matmul on CPU falls back to an int32 `torch.matmul` (several
          times slower than float32), so only its quantizer is used; the input projections
          (token, sentence, words) stay float32. Meant for CPU.

`inference_copy(transformer, precision)` returns a module for decoding only: the transformer
itself for fp32, otherwise a copy that shares every tensor it does not convert. The copy is
never trained nor saved: checkpoints, registry bundles and fingerprints always hold the float32
weights (`TextToMotion.transformer` stays the float32 module).
"""

from __future__ import annotations

import copy

import torch
from torch import nn

from mmm.generation.settings import DEFAULT_PRECISION, check_precision
from mmm.torchao_quiet import quiet_torchao_import


def default_precision(device: str | torch.device) -> str:
    """The precision used when none is asked for on this kind of device."""
    return DEFAULT_PRECISION.get(torch.device(device).type, "fp32")


def _torchao_int8():
    """torchao's Int8Tensor and PerRow (imported here: int8 only), without its import-time noise
    (its CUDA extensions are not needed for the quantizer: mmm.torchao_quiet)."""
    with quiet_torchao_import():
        from torchao.quantization import PerRow  # int8 only: torchao is loaded when first needed
        from torchao.quantization.quantize_.workflows.int8.int8_tensor import Int8Tensor  # idem

    return Int8Tensor, PerRow


class Int8Linear(nn.Module):
    """y = x W^T + b with int8 W (per output row scales) and x quantized per token at run time."""

    def __init__(self, linear: nn.Linear):
        super().__init__()
        Int8Tensor, PerRow = _torchao_int8()
        weight = linear.weight.detach().float()
        quantized = Int8Tensor.from_hp(weight, granularity=PerRow())
        self.in_features, self.out_features = linear.in_features, linear.out_features
        # (in, out) int8 as torch._int_mm takes it, and the per-row scales (out,)
        self.register_buffer("qweight_t", quantized.qdata.detach().t())
        self.register_buffer("scale", quantized.scale.detach().reshape(-1).float())
        self.register_buffer("bias", None if linear.bias is None else linear.bias.detach().float())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        shape = x.shape
        x = x.reshape(-1, shape[-1]).float()
        # max |x| per token: torch.linalg.vector_norm(x, inf) is the same value but 20% of an int8 pass
        step = x.abs().amax(dim=-1, keepdim=True).clamp_(min=1e-12).div_(127.0)
        q = torch.div(x, step).round_().clamp_(-127, 127).to(torch.int8)
        y = torch._int_mm(q, self.qweight_t).float().mul_(step).mul_(self.scale)
        if self.bias is not None:
            y.add_(self.bias)
        return y.view(*shape[:-1], self.out_features)

    def extra_repr(self) -> str:
        return f"in_features={self.in_features}, out_features={self.out_features}, int8"


def _bf16_linear(linear: nn.Linear) -> nn.Linear:
    out = nn.Linear(linear.in_features, linear.out_features, bias=linear.bias is not None, device="meta")
    out.weight = nn.Parameter(linear.weight.detach().to(torch.bfloat16), requires_grad=False)
    if linear.bias is not None:
        out.bias = nn.Parameter(linear.bias.detach().to(torch.bfloat16), requires_grad=False)
    return out


def _int8_targets(name: str) -> bool:
    """The attention/MLP linears and the head: where the weights are."""
    return name == "head" or name.startswith(("layers.", "cross_layers."))


def inference_copy(transformer: nn.Module, precision: str) -> nn.Module:
    """A module that decodes like `transformer` at `precision` (module docstring); for fp32 the
    transformer itself. The copy shares the tensors it does not convert and is in eval mode."""
    check_precision(precision)
    if precision == "fp32":
        return transformer
    shared = {id(t): t for t in (*transformer.parameters(), *transformer.buffers())}
    model = copy.deepcopy(transformer, memo=shared).eval()
    replaced = 0
    for name, module in list(model.named_modules()):
        if not isinstance(module, nn.Linear):
            continue
        if precision == "bf16":
            new = _bf16_linear(module)
        elif _int8_targets(name):
            new = Int8Linear(module)
        else:
            continue
        parent_name, _, child = name.rpartition(".")
        parent = model.get_submodule(parent_name) if parent_name else model
        if isinstance(parent, nn.Sequential):
            parent[int(child)] = new
        else:
            setattr(parent, child, new)
        replaced += 1
    if not replaced:
        raise ValueError(f"no linear layers to convert to {precision} in {type(transformer).__name__}")
    model.inference_autocast = torch.bfloat16 if precision == "bf16" else None
    model.inference_precision = precision
    return model
