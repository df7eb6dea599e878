"""The machine a command runs on: whether a device exists here (`check_device`) and whether
bfloat16 is fast on it (`has_fast_bf16`). Below every layer: the code search of the tokenizer,
inference precision and the config checks of evaluate, ablate and promote all ask."""

from __future__ import annotations

import torch


def cpu_has_bf16_matmul() -> bool | None:
    """Whether oneDNN has bfloat16 kernels for this CPU (AVX-512 and newer: AVX-512 BF16, AMX);
    None when this build of PyTorch cannot tell."""
    try:
        return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):
        return None


def has_fast_bf16() -> bool:
    """Whether bfloat16 runs faster than float32 here: a GPU that supports it, or a CPU with
    oneDNN's bfloat16 kernels (without them autocast emulates every matmul, slower than float32)."""
    if torch.cuda.is_available():
        return torch.cuda.is_bf16_supported()
    return bool(cpu_has_bf16_matmul())


def check_device(device: str | torch.device, key: str = "device") -> torch.device:
    """`device` as a torch.device when this machine can run on it (cpu, an available CUDA GPU, or
    Apple's mps), else a ValueError naming `key`, the value and the fix; never PyTorch's own
    "not compiled with CUDA" AssertionError halfway through loading a model."""
    try:
        parsed = torch.device(device)
    except (RuntimeError, TypeError):
        raise ValueError(
            f"{key}={device!r} is not a device: use cpu, or cuda / cuda:N on a machine with an NVIDIA GPU"
        ) from None
    if parsed.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0:
            raise ValueError(
                f"{key}={device!r}: no CUDA GPU is available here (PyTorch {torch.__version__}, CUDA build "
                f"{torch.version.cuda or 'none'}); use {key}=cpu"
            )
        if parsed.index is not None and parsed.index >= count:
            raise ValueError(
                f"{key}={device!r}: this machine has {count} CUDA GPU(s), cuda:0 to cuda:{count - 1}"
            )
    elif parsed.type == "mps":
        if not torch.backends.mps.is_available():
            raise ValueError(f"{key}={device!r}: Apple's mps backend is not available here; use {key}=cpu")
    elif parsed.type != "cpu":
        raise ValueError(f"{key}={device!r}: this package runs on cpu, cuda or mps, not {parsed.type}")
    return parsed
