"""The standard text-to-motion evaluation protocol (evaluation.md), for any embedding evaluator.

Per replication (20 by default): the test split shuffled into batches of 32 (drop_last), one
random caption per item, the length cut to a multiple of 4 (one unit shorter with probability
1/3), a motion generated at that length for the caption; then R-Precision top-1/2/3 and MM-Dist
(each text against the motion of its batch), FID (generated against real embeddings) and
Diversity. MultiModality: the first `mm_texts` items, each generated `mm_generations` times.
Each figure is reported as mean ± 1.96·std/sqrt(n) (population std) over the replications, for
the generated motions and for the real ones (the reference row).

An evaluator is anything with `embed_texts(captions: list[Caption]) -> (B, E)` and
`embed_motions(features (B, T, D) un-normalized, lengths (B,)) -> (B, E)`.

How a batch of motions is produced is a parameter (`produce`, a `Producer`): by default the model
generates each from its caption; the editing benchmarks (evaluation/editing.py) instead keep part
of the real motion and generate the rest, and are scored by the same replications.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable

import numpy as np
import torch
from tqdm import tqdm

from mmm.data.datasets import TextMotionDataset
from mmm.data.humanml3d import MotionItem
from mmm.evaluation.configs import ProtocolConfig
from mmm.evaluation.metrics import diversity, fid, matching_score, multimodality, r_precision_hits
from mmm.motion.features import pad_motions

log = logging.getLogger(__name__)

METRICS = ("top1", "top2", "top3", "fid", "matching_score", "diversity", "multimodality")

# produce(texts, lengths, real, seed) -> the generated motions of a batch: texts (B,) captions,
# lengths (B,) frames, real (B, T, D) the un-normalized real crops (the mean pose past each length), seed an
# int; returns (B, T', D) features or B arrays (T_i, D), un-normalized, each at least its length.
Producer = Callable[[list[str], list[int], torch.Tensor, int], "np.ndarray | list[np.ndarray]"]


def interval(values: list[float]) -> tuple[float, float]:
    """(mean, 1.96 · std / sqrt(n)) with the population std, as the protocol reports."""
    arr = np.asarray(values, dtype=np.float64)
    return float(arr.mean()), float(1.96 * arr.std() / math.sqrt(len(arr))) if len(arr) > 1 else 0.0


def _batches(dataset: TextMotionDataset, batch_size: int, seed: int, max_batches: int | None):
    """Shuffled batches (drop_last) of (item, sample) pairs."""
    order = torch.randperm(len(dataset), generator=torch.Generator().manual_seed(seed)).tolist()
    count = len(order) // batch_size
    if max_batches is not None:
        count = min(count, max_batches)
    for b in range(count):
        indices = order[b * batch_size : (b + 1) * batch_size]
        yield [(dataset.items[i], dataset[i + seed * len(dataset)]) for i in indices]


def _caption_of(item: MotionItem, text: str):
    return next(c for c in item.captions if c.text == text)


@torch.no_grad()
def evaluate_text_to_motion(
    model,
    evaluator,
    items: list[MotionItem],
    mean: np.ndarray,
    std: np.ndarray,
    cfg: ProtocolConfig,
    progress: bool = True,
    produce: Producer | None = None,
    multimodality: bool = True,
) -> dict:
    """Replicated protocol for a TextToMotion `model`; returns {"generated": {metric: (mean, ci)},
    "real": {...}, "replications": [...per replication dicts...]}.

    produce: how each batch's motions are made (see `Producer`); default: `model.generate` from the
    captions at the real lengths. multimodality=False skips MultiModality (reported as nan): an
    edit of one real motion has no set of generations per text to compare."""
    if len(items) < cfg.batch_size:
        raise ValueError(f"the split has {len(items)} items, fewer than one batch of {cfg.batch_size}")
    if produce is None:

        def produce(texts, lengths, real, seed):
            return model.generate(texts, lengths, cfg.sampling, seed=seed, check_lengths=False).features

    rows = []
    for rep in tqdm(range(cfg.replications), desc="evaluation replications", disable=not progress):
        seed = cfg.seed * 1000 + rep
        dataset = TextMotionDataset(
            items, mean, std, max_length=model.max_frames, unit_length=model.unit, random_crop=True, seed=seed
        )
        texts, real, gen = [], [], []
        for pairs in _batches(dataset, cfg.batch_size, seed, cfg.max_batches):
            batch = [b for _, b in pairs]
            captions = [_caption_of(item, b["caption"]) for item, b in pairs]
            lengths = torch.tensor([b["length"] for b in batch])
            features = torch.stack([torch.as_tensor(b["motion"].numpy() * std + mean) for b in _pad(batch)])
            out = produce(
                [c.text for c in captions], lengths.tolist(), features.float(), seed * 7919 + len(texts)
            )
            generated = torch.from_numpy(pad_motions(out, features.shape[1]))
            texts.append(evaluator.embed_texts(captions).cpu())
            real.append(evaluator.embed_motions(features.float(), lengths).cpu())
            gen.append(evaluator.embed_motions(generated.float(), lengths).cpu())
        rows.append(_score(texts, real, gen, cfg, seed))
    mm = _multimodality(model, evaluator, items, cfg, progress) if multimodality else (float("nan"), 0.0)
    result = {"generated": {}, "real": {}, "replications": rows}
    for which in ("generated", "real"):
        for metric in ("top1", "top2", "top3", "fid", "matching_score", "diversity"):
            result[which][metric] = interval([r[which][metric] for r in rows])
    result["generated"]["multimodality"] = mm
    return result


def _pad(batch: list[dict]) -> list[dict]:
    longest = max(b["length"] for b in batch)
    out = []
    for b in batch:
        m = b["motion"]
        if m.shape[0] < longest:
            m = torch.cat((m, torch.zeros(longest - m.shape[0], m.shape[1])))
        out.append({**b, "motion": m})
    return out


def _score(texts, real, gen, cfg: ProtocolConfig, seed: int) -> dict:
    generator = torch.Generator().manual_seed(seed)
    t, r, g = torch.cat(texts), torch.cat(real), torch.cat(gen)
    row = {}
    for which, motions in (("real", r), ("generated", g)):
        hits = sum(r_precision_hits(tb, mb, 3) for tb, mb in zip(texts, real if which == "real" else gen))
        n = sum(len(tb) for tb in texts)
        row[which] = {
            "top1": float(hits[0]) / n,
            "top2": float(hits[1]) / n,
            "top3": float(hits[2]) / n,
            "matching_score": float(matching_score(t, motions)),
            "fid": float(fid(r, motions)),
            "diversity": float(diversity(motions, min(cfg.diversity_times, len(motions)), generator)),
        }
    return row


def _multimodality(model, evaluator, items, cfg: ProtocolConfig, progress: bool) -> tuple[float, float]:
    """Mean and interval over replications of MultiModality on the first mm_texts items."""
    if cfg.mm_texts <= 0 or cfg.mm_generations < 2:
        return (float("nan"), 0.0)
    chosen = items[: cfg.mm_texts]
    values = []
    for rep in range(cfg.replications):
        embeddings = []
        for k, item in enumerate(chosen):
            frames = min(item.length, model.max_frames) // model.unit * model.unit
            out = model.generate(
                [item.captions[0].text] * cfg.mm_generations,
                [frames] * cfg.mm_generations,
                cfg.sampling,
                seed=cfg.seed * 100_003 + rep * 1009 + k,
                check_lengths=False,
            )
            lengths = torch.full((cfg.mm_generations,), frames)
            embeddings.append(
                evaluator.embed_motions(torch.from_numpy(np.stack(out.features)).float(), lengths).cpu()
            )
        generator = torch.Generator().manual_seed(cfg.seed * 31 + rep)
        values.append(
            float(multimodality(torch.stack(embeddings), min(cfg.mm_times, cfg.mm_generations), generator))
        )
    return interval(values)


def results_table(results: dict[str, dict], title: str = "") -> str:
    """Markdown table in the paper's layout: one row per entry, mean ± interval per metric."""
    head = "| | R-Precision top-1 | top-2 | top-3 | FID | MM-Dist | Diversity | MultiModality |"
    lines = ([f"**{title}**", ""] if title else []) + [head, "|---|---|---|---|---|---|---|---|"]
    for name, row in results.items():
        cells = []
        for metric in METRICS:
            value = row.get(metric)
            if value is None or math.isnan(value[0]):
                cells.append("-")
            else:
                cells.append(
                    f"{value[0]:.3f} ± {value[1]:.3f}".replace("-0.000 ", "0.000 ")
                )  # FID of real vs real: rounding noise
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)
