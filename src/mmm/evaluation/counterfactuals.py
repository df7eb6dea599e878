"""Does an evaluator read counts and speeds? `counterfactual_ranking`: how often a real motion's
own caption scores above its counterfactuals (mmm.text.counterfactuals: the same caption with its
count or speed word changed), logged by `mmm train evaluator` as `test/counterfactual_*_first`.

The same counterfactuals are the evaluator's hard negatives in training (`loss.counterfactuals`),
since in-batch negatives rarely hold the same action at another count (measured in the README,
"Best of N": it reads counts better and is not a better judge of draws), and best of N scores a
draw by its caption's margin over them (mmm.generation.best_of.counterfactual_margins).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from mmm.motion.features import pad_motions
from mmm.text.counterfactuals import KINDS, counterfactual_captions


@torch.no_grad()
def counterfactual_ranking(judge, items, batch_size: int = 64) -> dict[str, dict]:
    """How often an evaluator ranks a real motion's own caption above all of its counterfactuals.

    judge: an EvaluatorEmbedder (embed_texts on strings, embed_motions on raw features); items:
    MotionItems (.features (T, D) raw, .length, .captions). Per kind ("count", "speed"):
    {"captions": how many captions had counterfactuals of that kind, "first": the share whose own
    wording scored highest, "chance": the mean of 1 / (1 + variants)}; kinds with no caption are
    left out.
    """
    pairs = {kind: [] for kind in KINDS}  # (item index, caption, variants)
    for i, item in enumerate(items):
        for caption in item.captions:
            text = getattr(caption, "text", caption)
            for kind in KINDS:
                variants = counterfactual_captions(text, (kind,))
                if variants:
                    pairs[kind].append((i, text, variants))
    needed = sorted({i for rows in pairs.values() for i, _, _ in rows})
    motions = {}
    for start in range(0, len(needed), batch_size):
        chunk = needed[start : start + batch_size]
        lengths = [items[i].length for i in chunk]
        features = pad_motions([items[i].features[: items[i].length] for i in chunk])
        for i, z in zip(chunk, F.normalize(judge.embed_motions(features, lengths), dim=-1)):
            motions[i] = z
    texts = sorted({t for rows in pairs.values() for _, c, v in rows for t in (c, *v)})
    embedded = {}
    for start in range(0, len(texts), 256):
        chunk = texts[start : start + 256]
        embedded.update(zip(chunk, F.normalize(judge.embed_texts(chunk), dim=-1)))
    result = {}
    for kind, rows in pairs.items():
        if not rows:
            continue
        first = [
            all(float(motions[i] @ embedded[c]) > float(motions[i] @ embedded[v]) for v in variants)
            for i, c, variants in rows
        ]
        result[kind] = {
            "captions": len(rows),
            "first": float(np.mean(first)),
            "chance": float(np.mean([1 / (1 + len(v)) for _, _, v in rows])),
        }
    return result
