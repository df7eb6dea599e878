"""Confidence-based parallel decoding (MMM inference) with per-sample iteration counts.

A sample of L codes starts with its free positions set to MASK (kept positions, for editing, hold
their codes). Sample b runs T_b = ceil(T_max * L_b / M) iterations (M = the model's 50 token
positions), so short motions take fewer passes. At iteration t of T_b the model predicts every
masked position, a code is drawn at each from softmax(logits / temperature) after optional top-k
(a fraction of the codebook) and top-p filtering, its probability is its confidence; positions
fixed before (kept or decoded earlier) have infinite confidence; then the n(t) = ceil(gamma(t/T_b)
* F_b) least confident positions are masked again (F_b = free positions). A sample whose
iterations are done takes no further forward passes; a batch of mixed lengths costs max_b T_b
passes. Classifier-free guidance: logits = uncond + s * (cond - uncond), the two branches in one
batched pass.

`decoding="released"` runs the authors' released loop instead (`sample_tokens_released`), so
outputs and speed can be compared like for like with imported weights: every sample starts from
the model's full M positions; S = round(T_max * L / 49) steps per sample; at step s, with
t = min(s / S, 1), the n = max(floor(cos(pi/2 * t) * L), 1) positions of highest score are
masked (score = 1 - probability of the code drawn at the previous step where one was drawn, 0
elsewhere; every position at step 0), then one pass draws a code at every masked position by
Gumbel-max at the temperature (argmax at 0; no top-k, top-p or guidance). A batch of one stops
early by the release's test `min(s - 1 / S, 1) == t` (the passes this gives: 10 for L <= 2, 2 for
L 3-7, 1 for L 8-12, S from 13 on); larger batches always run T_max steps, finished samples
re-predicting one position per step. Same generator and logits as the release: the same codes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from mmm.generation.settings import SamplingConfig
from mmm.transformer.schedules import DECODING_SCHEDULES


@dataclass
class DecodeTrace:
    """Per iteration: which samples ran, every position's confidence and what stayed masked."""

    active: list[torch.Tensor] = field(default_factory=list)  # (B,) bool
    confidence: list[torch.Tensor] = field(default_factory=list)  # (B, M), nan where not predicted
    masked: list[torch.Tensor] = field(default_factory=list)  # (B, M) bool after re-masking
    tokens: list[torch.Tensor] = field(default_factory=list)  # (B, M)


@dataclass
class SampleResult:
    tokens: torch.Tensor  # (B, M): codes, END, PAD
    lengths: torch.Tensor  # (B,) codes per sample
    iterations: torch.Tensor  # (B,) forward passes each sample took part in
    forward_passes: int  # transformer passes for the whole batch (= max of iterations)
    trace: DecodeTrace | None = None


def iteration_counts(
    code_lengths: torch.Tensor, free: torch.Tensor, cfg: SamplingConfig, max_tokens: int
) -> torch.Tensor:
    """(B,) iterations: ceil(T_max * L / M), at least 1; 0 when nothing is free to decode."""
    if cfg.dynamic_iterations:
        counts = torch.ceil(cfg.max_iterations * code_lengths.float() / max_tokens).long().clamp(min=1)
    else:
        counts = torch.full_like(code_lengths, cfg.max_iterations)
    return torch.where(free > 0, counts, torch.zeros_like(counts))


def filter_logits(logits: torch.Tensor, top_k: float | None, top_p: float | None) -> torch.Tensor:
    """Set to -inf the logits outside the top-k fraction and outside the top-p nucleus (..., K)."""
    K = logits.shape[-1]
    if top_k is not None and top_k < 1.0:
        k = max(1, int(round(top_k * K)))
        kth = logits.topk(k, dim=-1).values[..., -1:]
        logits = logits.masked_fill(logits < kth, float("-inf"))
    if top_p is not None and top_p < 1.0:
        sorted_logits, order = logits.sort(dim=-1, descending=True)
        cumulative = sorted_logits.softmax(-1).cumsum(-1)
        drop_sorted = (cumulative - sorted_logits.softmax(-1)) >= top_p  # keeps the first code always
        drop = torch.zeros_like(drop_sorted).scatter(-1, order, drop_sorted)
        logits = logits.masked_fill(drop, float("-inf"))
    return logits


def draw_codes(probs: torch.Tensor, at: torch.Tensor, positions: int, generator) -> torch.Tensor:
    """One code per row of probs (N, K), the rows being positions `at` (N,) of the pass's `positions`:
    argmax(p / q), q = -log(u) ~ Exp(1), torch.multinomial's own rule for one draw.

    Every position of the pass gets its noise u (positions, K) ~ U[0, 1) whether it draws or not, so
    a position's draw does not depend on which others are masked: two runs whose probabilities differ
    a little (two precisions) draw the same codes for the same seed except where the two best p / q
    are that close. Noise only for the masked positions, in their order, shifted every later draw
    once a single code differed (identical codes int8 vs fp32 at the paper size: 75% against 92%);
    an inverse-CDF draw, one uniform per position, moved codes under any small change (24%).
    `uniform_` with the log taken where codes are drawn is 4x cheaper on this CPU than the
    `exponential_` torch.multinomial takes, which was 8-12% of an int8 decoding pass."""
    u = torch.empty(positions, probs.shape[-1], device=probs.device).uniform_(generator=generator)
    return (probs / u.index_select(0, at).log_().neg_()).argmax(-1)


@torch.no_grad()
def sample_tokens(
    model,
    text,
    code_lengths: torch.Tensor,
    cfg: SamplingConfig,
    *,
    keep_tokens: torch.Tensor | None = None,
    keep_mask: torch.Tensor | None = None,
    no_text: torch.Tensor | None = None,
    condition: torch.Tensor | None = None,
    generator: torch.Generator | None = None,
    trace: bool = False,
    reference: bool = False,
) -> SampleResult:
    """Decode codes for a batch.

    model: a MaskedMotionTransformer (eval). text: TextEmbedding of the batch. code_lengths (B,):
    codes per sample (ceil(frames / 4)). keep_tokens/keep_mask (B, >= max L): codes that are given
    and never change (editing). no_text (B,) True: decode without text (the unconditional branch).
    condition (B, >= max L): a part-aware model's lower-body codes (its MASK id where hidden).

    A model with `text_context`/`forward_cached` (MaskedMotionTransformer and its inference
    copies, mmm.generation.precision) decodes with less work per pass (`_decode_cached`): the
    words' cross-attention keys/values once per sample, the head only where codes are drawn, no
    host synchronization inside the loop; the same codes as the plain loop (`reference=True`, or
    a model with only `forward`) for the same seed in float32.
    """
    if cfg.decoding == "released":
        if no_text is not None and bool(no_text.any()) or condition is not None or trace:
            raise ValueError(
                "the released decoding takes text-conditioned whole-body samples only (no edits without "
                "text, "
                "part-aware conditions or traces): use decoding=package"
            )
        return sample_tokens_released(
            model, text, code_lengths, cfg, keep_tokens=keep_tokens, keep_mask=keep_mask, generator=generator
        )
    device = code_lengths.device
    B = len(code_lengths)
    K, M_model = model.num_codes, model.cfg.max_tokens
    mask_id, end_id, pad_id = model.mask_id, model.end_id, model.pad_id
    if int(code_lengths.max()) > M_model - 1 or int(code_lengths.min()) < 1:
        raise ValueError(f"code lengths must be in 1..{M_model - 1}, got {code_lengths.tolist()}")
    M = int(code_lengths.max()) + 1
    positions = torch.arange(M, device=device)
    real = positions[None] < code_lengths[:, None]
    tokens = torch.full((B, M), pad_id, dtype=torch.long, device=device)
    tokens[real] = mask_id
    tokens[positions[None] == code_lengths[:, None]] = end_id
    fixed = torch.zeros(B, M, dtype=torch.bool, device=device)
    if keep_mask is not None:
        n = min(M, keep_mask.shape[1])
        keep = torch.zeros(B, M, dtype=torch.bool, device=device)
        keep[:, :n] = keep_mask[:, :n].to(device)
        keep &= real
        given = torch.zeros(B, M, dtype=torch.long, device=device)
        given[:, :n] = keep_tokens[:, :n].to(device)
        tokens = torch.where(keep, given, tokens)
        fixed = keep
    cond = None
    if condition is not None:
        c = model.condition
        cond = torch.full((B, M), c.pad_id, dtype=torch.long, device=device)
        n = min(M, condition.shape[1])
        cond[:, :n] = torch.where(real[:, :n], condition[:, :n].to(device), cond[:, :n])
        cond[positions[None].expand(B, M) == code_lengths[:, None]] = c.end_id
    free = (real & ~fixed).sum(1)
    iterations = iteration_counts(code_lengths, free, cfg, M_model)
    gamma = DECODING_SCHEDULES[cfg.schedule]
    no_text = torch.zeros(B, dtype=torch.bool, device=device) if no_text is None else no_text.to(device)
    guided = cfg.guidance_scale != 1.0
    record = DecodeTrace() if trace else None
    passes = int(iterations.max()) if B else 0
    if not reference and hasattr(model, "forward_cached"):
        return _decode_cached(
            model, text, tokens, cond, free, iterations, code_lengths, no_text, cfg, generator, record
        )
    for step in range(passes):
        active = step < iterations
        idx = active.nonzero().squeeze(1)
        sub = tokens[idx]
        sentence, words, word_mask = text.sentence[idx], text.words[idx], text.word_mask[idx]
        drop = no_text[idx]
        sub_condition = None if cond is None else cond[idx]
        if guided:
            both = model(
                torch.cat((sub, sub)),
                torch.cat((sentence, sentence)),
                torch.cat((words, words)),
                torch.cat((word_mask, word_mask)),
                torch.cat((drop, torch.ones_like(drop))),
                None if sub_condition is None else torch.cat((sub_condition, sub_condition)),
            )
            with_text, without_text = both.chunk(2)
            logits = torch.where(
                drop[:, None, None], with_text, without_text + cfg.guidance_scale * (with_text - without_text)
            )
        else:
            logits = model(sub, sentence, words, word_mask, drop, sub_condition)
        logits = filter_logits(logits.float(), cfg.top_k, cfg.top_p)
        masked = sub == mask_id
        if cfg.temperature <= 0:
            sampled = logits.argmax(-1)
            probs = logits.softmax(-1)
        else:
            probs = (logits / cfg.temperature).softmax(-1)
            drawn_at = masked.flatten().nonzero().squeeze(1)
            sampled = torch.zeros(sub.numel(), dtype=torch.long, device=device)
            sampled[drawn_at] = draw_codes(probs.view(-1, K)[drawn_at], drawn_at, sub.numel(), generator)
            sampled = sampled.view(sub.shape)
        confidence = probs.gather(-1, sampled.unsqueeze(-1)).squeeze(-1)
        decoded = torch.where(masked, sampled, sub)
        confidence = torch.where(masked, confidence, torch.full_like(confidence, float("inf")))
        # Positions still masked after this iteration: ceil(gamma(t / T_b) * F_b).
        t = (step + 1) / iterations[idx].float()
        remain = (
            torch.ceil(torch.tensor([gamma(float(x)) for x in t], device=device) * free[idx].float() - 1e-6)
            .long()
            .clamp(min=0)
        )
        rank = confidence.argsort(dim=1).argsort(dim=1)
        remask = rank < remain[:, None]
        decoded = torch.where(remask, torch.full_like(decoded, mask_id), decoded)
        tokens[idx] = decoded
        if record is not None:
            conf_full = torch.full((B, M), float("nan"), device=device)
            conf_full[idx] = torch.where(masked, confidence, torch.full_like(confidence, float("nan")))
            record.active.append(active.cpu())
            record.confidence.append(conf_full.cpu())
            record.masked.append((tokens == mask_id).cpu())
            record.tokens.append(tokens.cpu())
    return SampleResult(tokens, code_lengths, iterations, passes, record)


def _remaining_masked(
    iterations: torch.Tensor, free: torch.Tensor, gamma, passes: int
) -> tuple[torch.Tensor, list[list[int]]]:
    """(passes, B) the positions each sample keeps masked after each pass, 0 where it does not
    run, with the reference loop's arithmetic (float32 progress, the schedule in float64, float32
    product), on the host before the loop; and the rows that run in each pass."""
    iterations, free = iterations.cpu(), free.cpu()
    B = len(iterations)
    remain = torch.zeros(passes, B, dtype=torch.long)
    active: list[list[int]] = []
    for step in range(passes):
        idx = (step < iterations).nonzero().squeeze(1)
        t = (step + 1) / iterations[idx].float()
        remain[step, idx] = (
            torch.ceil(torch.tensor([gamma(float(x)) for x in t]) * free[idx].float() - 1e-6)
            .long()
            .clamp(min=0)
        )
        active.append(idx.tolist())
    return remain, active


def _decode_cached(
    model, text, tokens, cond, free, iterations, code_lengths, no_text, cfg: SamplingConfig, generator, record
) -> SampleResult:
    """The decoding loop of `sample_tokens` with less work per pass, the same codes.

    Everything that depends on the data only through counts (which rows run, how many positions
    stay masked) is planned on the host before the loop; the loop itself only queues device work.
    Codes are drawn by `draw_codes` with noise for every position of the rows that run, read at the
    masked ones, as the reference loop draws them, so the generator is consumed exactly as there."""
    device = tokens.device
    B, M = tokens.shape
    mask_id = model.mask_id
    passes = int(iterations.max()) if B else 0
    gamma = DECODING_SCHEDULES[cfg.schedule]
    remain_all, active = _remaining_masked(iterations, free, gamma, passes)
    # Positions masked at the start of each pass, per sample: the free ones, then what the previous
    # pass left masked.
    masked_before = torch.cat((free.cpu()[None], remain_all[:-1]), dim=0) if passes else remain_all
    guided = cfg.guidance_scale != 1.0
    if guided:
        context = model.text_context(
            torch.cat((text.sentence, text.sentence)),
            torch.cat((text.words, text.words)),
            torch.cat((text.word_mask, text.word_mask)),
            torch.cat((no_text, torch.ones_like(no_text))),
        )
    else:
        context = model.text_context(text.sentence, text.words, text.word_mask, no_text)
    remain_all = remain_all.to(device)
    plans = []
    for step in range(passes):  # the host plan: rows, their index tensors, masked counts
        rows = active[step]
        everyone = len(rows) == B
        idx = None if everyone else torch.tensor(rows, dtype=torch.long, device=device)
        if step and plans[-1][1] == rows:
            idx, sub_context = plans[-1][2], plans[-1][3]
        elif guided:
            sub_context = context.select(None if everyone else torch.cat((idx, idx + B)))
        else:
            sub_context = context.select(idx)
        plans.append((step, rows, idx, sub_context, int(masked_before[step, rows].sum())))
    no_text_rows = no_text.repeat_interleave(M)
    for step, rows, idx, sub_context, count in plans:
        b = len(rows)
        sub = tokens if idx is None else tokens.index_select(0, idx)
        sub_condition = None if cond is None else (cond if idx is None else cond.index_select(0, idx))
        masked = sub == mask_id
        # The masked positions in row-major order (a stable sort puts them first): no host sync.
        head_rows = torch.argsort((~masked).flatten().to(torch.uint8), stable=True)[:count]
        if guided:
            both = model.forward_cached(
                torch.cat((sub, sub)),
                sub_context,
                None if sub_condition is None else torch.cat((sub_condition, sub_condition)),
                torch.cat((head_rows, head_rows + b * M)),
            )
            with_text, without_text = both.chunk(2)
            dropped = (no_text_rows if idx is None else no_text.index_select(0, idx).repeat_interleave(M))[
                head_rows
            ]
            logits = torch.where(
                dropped[:, None], with_text, without_text + cfg.guidance_scale * (with_text - without_text)
            )
        else:
            logits = model.forward_cached(sub, sub_context, sub_condition, head_rows)
        logits = filter_logits(logits, cfg.top_k, cfg.top_p)
        if cfg.temperature <= 0:
            sampled = logits.argmax(-1)
            probs = logits.softmax(-1)
        else:
            probs = (logits / cfg.temperature).softmax(-1)
            sampled = draw_codes(probs, head_rows, b * M, generator)
        drawn = probs.gather(-1, sampled.unsqueeze(-1)).squeeze(-1)
        confidence = (
            torch.full((b * M,), float("inf"), device=device).index_copy(0, head_rows, drawn).view(b, M)
        )
        decoded = sub.flatten().index_copy(0, head_rows, sampled).view(b, M)
        remain = remain_all[step] if idx is None else remain_all[step].index_select(0, idx)
        rank = confidence.argsort(dim=1).argsort(dim=1)
        decoded = torch.where(rank < remain[:, None], torch.full_like(decoded, mask_id), decoded)
        tokens = decoded if idx is None else tokens.index_copy(0, idx, decoded)
        if record is not None:
            conf_full = torch.full((B, M), float("nan"), device=device)
            conf_rows = torch.where(masked, confidence, torch.full_like(confidence, float("nan")))
            conf_full[rows] = conf_rows
            record.active.append((step < iterations).cpu())
            record.confidence.append(conf_full.cpu())
            record.masked.append((tokens == mask_id).cpu())
            record.tokens.append(tokens.cpu())
    return SampleResult(tokens, code_lengths, iterations, passes, record)


@torch.no_grad()
def sample_tokens_released(
    model,
    text,
    code_lengths: torch.Tensor,
    cfg: SamplingConfig,
    *,
    keep_tokens: torch.Tensor | None = None,
    keep_mask: torch.Tensor | None = None,
    generator: torch.Generator | None = None,
) -> SampleResult:
    """The released decoding loop (module docstring), op for op, on (B, M) with M the model's
    token positions. keep_tokens/keep_mask (B, >= max L): codes given and never re-masked (the
    release's `token_cond`); the masked counts then run over the free positions."""
    device = code_lengths.device
    B, M = len(code_lengths), model.cfg.max_tokens
    mask_id, end_id, pad_id = model.mask_id, model.end_id, model.pad_id
    if int(code_lengths.max()) > M - 1 or int(code_lengths.min()) < 1:
        raise ValueError(f"code lengths must be in 1..{M - 1}, got {code_lengths.tolist()}")
    lengths = code_lengths.long()
    positions = torch.arange(M, device=device)[None]
    visible = positions < (lengths + 1)[:, None]  # codes and END
    real = positions < lengths[:, None]
    ids = torch.full((B, M), mask_id, dtype=torch.long, device=device)
    kept = torch.zeros(B, M, dtype=torch.bool, device=device)
    if keep_mask is not None:
        n = min(M, keep_mask.shape[1])
        kept[:, :n] = keep_mask[:, :n].to(device) & real[:, :n]
        ids[:, :n] = torch.where(kept[:, :n], keep_tokens[:, :n].to(device), ids[:, :n])
    free = (real & ~kept).sum(1)
    ids[~visible] = pad_id
    ids.scatter_(-1, lengths[:, None], end_id)
    scores = torch.ones(B, M, device=device)
    steps = torch.round(cfg.max_iterations / 49 * lengths) + 1e-8  # S, as a float32 tensor like the release's
    passes = 0
    for step in range(cfg.max_iterations):
        t = torch.clip(step / steps, max=1)
        if B == 1 and step > 0 and torch.clip(step - 1 / steps, max=1).item() == t.item():
            break  # the release's early exit for a batch of one (its precedence slip included)
        count = (
            (torch.cos(t * math.pi * 0.5) * (free if keep_mask is not None else lengths)).long().clip(min=1)
        )
        scores[kept] = 0
        scores[~real] = 0
        scores = scores / scores.sum(-1)[:, None]
        order = scores.sort(descending=True).indices
        ids[~visible] = pad_id
        ids.scatter_(-1, lengths[:, None], end_id)
        chosen = positions < count[:, None]
        last = order.gather(-1, (count - 1)[:, None])
        ids.scatter_(-1, order * chosen + last * ~chosen, mask_id)
        logits = model(ids, text.sentence, text.words, text.word_mask)
        uniform = torch.zeros_like(logits).uniform_(0, 1, generator=generator)
        noise = -torch.log(
            (-torch.log(uniform.clamp(min=1e-20))).clamp(min=1e-20)
        )  # Gumbel, clamped as the release does
        drawn = (logits / max(cfg.temperature, 1e-10) + noise).argmax(-1)
        masked = ids == mask_id
        ids = torch.where(masked, drawn, ids)
        scores = (1 - logits.softmax(-1).gather(-1, drawn[..., None])[..., 0]).masked_fill(~masked, 0)
        passes += 1
    return SampleResult(ids, code_lengths, torch.full((B,), passes, dtype=torch.long, device=device), passes)


def frames_to_codes(frames: torch.Tensor | int, unit_length: int = 4) -> torch.Tensor:
    """Codes for a motion of `frames` frames: ceil(frames / unit_length)."""
    frames = torch.as_tensor(frames)
    return torch.div(frames + unit_length - 1, unit_length, rounding_mode="floor")
