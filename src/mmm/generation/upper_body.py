"""Upper-body editing with a part-aware model (supplementary I.2, Figure 14).

The source motion is tokenized into lower-body and upper-body codes. The lower-body codes are the
condition: all of them, or only some (`lower_keep` frame ranges, or a random `lower_mask` share
hidden), and the transformer decodes new upper-body codes from the text given that condition. The
output decodes the source's lower-body codes everywhere with the new upper-body codes, so the legs
and the root path are the source's (up to the tokenizer's reconstruction error) and only the
condition's strength changes how the upper body is allowed to move: the more lower-body codes
are hidden, the less the generated arms and torso have to agree with what the legs do.

Classifier-free guidance carries the text against a visible lower body: on the synthetic data,
where every lower-body action comes with one upper-body motion in training, the legs alone
decide the arms unless the text is amplified, so edits default to guidance scale 4 (measured in
the README: the requested upper action in 3% of edits with the whole lower body shown and no
guidance, 86% with half of it hidden and guidance 4).
"""

from __future__ import annotations

import time

import numpy as np
import torch

from mmm.generation.sampler import SamplingConfig, sample_tokens

UPPER_BODY_GUIDANCE = 4.0  # default classifier-free guidance scale of upper-body edits
DEFAULT_LOWER_MASK = 0.5  # default share of the source's lower-body codes hidden


def lower_condition(
    lower: np.ndarray,
    mask_id: int,
    lower_mask: float | None,
    keep: np.ndarray | None,
    generator: torch.Generator,
    samples: int,
) -> torch.Tensor:
    """(samples, L) condition codes: `lower` (L,) with MASK where hidden. keep (L,) bool: codes
    shown (the rest hidden); else round(lower_mask * L) codes hidden, drawn per sample."""
    L = len(lower)
    codes = torch.as_tensor(lower.astype(np.int64)).expand(samples, L).clone()
    if keep is not None:
        hidden = ~torch.as_tensor(keep).expand(samples, L)
    else:
        count = int(round((lower_mask or 0.0) * L))
        order = torch.stack([torch.randperm(L, generator=generator) for _ in range(samples)])
        hidden = order < count  # a random `count` positions per sample
    return torch.where(hidden, torch.full_like(codes, mask_id), codes)


@torch.no_grad()
def edit_upper_body(
    model,
    source: np.ndarray,
    text: str,
    lower_mask: float | None = None,
    lower_keep: list[tuple[int, int]] | None = None,
    sampling: SamplingConfig | None = None,
    seed: int | None = None,
    num_samples: int = 1,
    check_lengths: bool = True,
):
    """New upper body for `source` (un-normalized features (T, 263)) from `text`, keeping its
    lower body. `model` is a TextToMotion whose tokenizer and transformer are part-aware.

    lower_mask: the share of lower-body codes hidden from the transformer (0: the whole lower
    body constrains the upper body, 1: only the text does); lower_keep: frame ranges [a, b) whose
    lower-body codes are shown, the rest hidden. At most one of the two; neither means 0.
    sampling: default SamplingConfig(guidance_scale=UPPER_BODY_GUIDANCE). check_lengths=False
    admits sources shorter than the model's minimum (the evaluation protocol's crops), as `generate`.
    Returns Generated (features (T', 263), joints, codes (L, 2) [lower, upper]; T' = T cut to a
    multiple of 4) with `kept_codes` (samples, L): the lower-body codes each sample was shown.
    """
    if not model.part_aware:
        raise ValueError(
            "upper-body editing needs a part-aware model (stage 1 with model.tokenizer.part_aware=true, "
            "stage 2 trained on it); "
            "this one tokenizes the whole body at once"
        )
    if lower_mask is not None and lower_keep is not None:
        raise ValueError(
            "give either lower_mask (a share of lower-body codes to hide) or lower_keep (frame ranges to "
            "show), not both"
        )
    if lower_mask is not None and not 0.0 <= lower_mask <= 1.0:
        raise ValueError(f"lower_mask is a share in [0, 1], got {lower_mask}")
    if source.ndim != 2 or source.shape[1] != model.feature_dim:
        raise ValueError(f"source features have shape {source.shape}, expected (T, {model.feature_dim})")
    frames = source.shape[0] // model.unit * model.unit
    if check_lengths:
        model.check_frames(frames, "source length")
    elif not model.unit <= frames <= model.max_frames:
        raise ValueError(f"source length {frames} frames is outside {model.unit}..{model.max_frames}")
    if not text or not text.strip():
        raise ValueError("upper-body editing needs a text saying what the upper body does")
    sampling = sampling or SamplingConfig(guidance_scale=UPPER_BODY_GUIDANCE)
    started = time.perf_counter()
    codes = model.encode_motion(source)  # (L, 2): lower, upper
    L = len(codes)
    keep = None
    if lower_keep is not None:
        for a, b in lower_keep:
            if b > frames:
                raise ValueError(f"lower-keep range {a}:{b} goes past the source's {frames} usable frames")
        keep = model.keep_mask(L, lower_keep)
    generator = torch.Generator().manual_seed(
        seed if seed is not None else int(np.random.default_rng().integers(2**62))
    )
    condition = lower_condition(
        codes[:, 0], model.transformer.condition.mask_id, lower_mask, keep, generator, num_samples
    )
    texts = [text] * num_samples
    emb = model.encode_text(texts)
    seconds = {"text": time.perf_counter() - started}
    t0 = time.perf_counter()
    lengths = torch.full((num_samples,), L, dtype=torch.long, device=model.device)
    device_generator = torch.Generator(device=model.device).manual_seed(seed) if seed is not None else None
    result = sample_tokens(
        model.inference_transformer,
        emb,
        lengths,
        sampling,
        condition=condition.to(model.device),
        generator=device_generator,
    )
    model._sync()
    seconds["sample"] = time.perf_counter() - t0
    # Decode the source's lower-body codes with the generated upper-body codes.
    upper = result.tokens[:, :L].clone()
    result.tokens = torch.stack(
        (torch.as_tensor(codes[:, 0].astype(np.int64), device=upper.device).expand_as(upper), upper), dim=-1
    )
    out = model._finish(texts, result, [frames] * num_samples, seconds, started)
    out.kept_codes = (condition != model.transformer.condition.mask_id).numpy()  # (samples, L)
    return out
