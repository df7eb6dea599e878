"""Load an embedding evaluator for the protocol: the package's own or the standard T2M one.

    None / path / RUN_ID / runs:/ID / models:/NAME@ALIAS   the own contrastive evaluator
                                                            (default: the newest `make train-evaluator` run)
    t2m:DIR                                                 the standard evaluator from the files
                                                            you provide (DIR holds text_mot_match/;
                                                            glove_dir and norm_dir name the rest)

Both expose `embed_texts(captions)` and `embed_motions(features (B, T, D) un-normalized,
lengths)` and an `identity` (a fingerprint of the weights) that results and promotion record.
"""

from __future__ import annotations

from pathlib import Path

import torch

from mmm.evaluation.contrastive import EvaluatorEmbedder
from mmm.evaluation.t2m import T2MEvaluator, load_mean_std
from mmm.fingerprint import tensors_fingerprint
from mmm.kinds import EVALUATOR
from mmm.resolve import champion_reference, resolve_model

EVALUATOR_EXPERIMENT = EVALUATOR.experiment


class T2MEmbedder:
    """The standard evaluator behind the protocol's interface: captions' word/POS tokens, and
    motions mapped into the evaluator's own normalization, x_eval = (x - mean_e) / std_e."""

    name = "t2m"

    def __init__(self, evaluator, eval_mean, eval_std, device: str | torch.device = "cpu"):
        self.device = torch.device(device)
        self.evaluator = evaluator.to(self.device).eval()
        self.mean = torch.as_tensor(eval_mean, dtype=torch.float32, device=self.device)
        self.std = torch.as_tensor(eval_std, dtype=torch.float32, device=self.device)
        self.identity = "t2m-" + tensors_fingerprint(evaluator.state_dict())

    @torch.no_grad()
    def embed_texts(self, captions) -> torch.Tensor:
        missing = [c.text for c in captions if not getattr(c, "tokens", None)]
        if missing:
            raise ValueError(
                f"the standard evaluator needs word/POS tokens, and caption {missing[0]!r} has none (its "
                "caption line lacks them)"
            )
        return self.evaluator.embed_texts([list(c.tokens) for c in captions])

    @torch.no_grad()
    def embed_motions(self, features, lengths) -> torch.Tensor:
        x = (torch.as_tensor(features, dtype=torch.float32, device=self.device) - self.mean) / self.std
        return self.evaluator.embed_motions(x, torch.as_tensor(lengths))


def load_evaluator(
    reference: str | None,
    tracking_uri: str,
    device: str = "cpu",
    glove_dir: str | None = None,
    norm_dir: str | None = None,
):
    """An evaluator for the protocol (see the module docstring)."""
    if reference is not None and reference.startswith("t2m:"):
        directory = Path(reference[len("t2m:") :])
        if glove_dir is None or norm_dir is None:
            raise ValueError(
                "the standard evaluator needs evaluator.glove_dir (the folder with our_vab_data.npy, "
                "our_vab_words.pkl, our_vab_idx.pkl) "
                "and evaluator.norm_dir (its mean.npy/std.npy, e.g. "
                "checkpoints/t2m/VQVAEV3_CB1024_CMT_H1024_NRES3/meta)"
            )
        mean, std = load_mean_std(norm_dir)
        return T2MEmbedder(T2MEvaluator.load(directory, glove_dir), mean, std, device)

    _, checkpoint, _ = resolve_model(reference, tracking_uri, EVALUATOR, "evaluator")
    embedder = EvaluatorEmbedder.from_checkpoint(checkpoint, device=device)
    embedder.identity = "contrastive-" + tensors_fingerprint(embedder.evaluator.state_dict())
    embedder.name = "contrastive"
    return embedder


def load_judge(reference: str | None, tracking_uri: str, device: str = "cpu"):
    """The package's evaluator as the judge of best of N (mmm.generation.best_of): a checkpoint
    path, run id or models:/ reference; by default the evaluator champion, else the newest run."""
    if reference is not None and reference.startswith("t2m:"):
        raise ValueError(
            f"judge {reference}: the standard T2M evaluator reads tagged captions, not strings; best of N "
            "needs the package's own evaluator (a path, run id or models:/mmm-evaluator@champion)"
        )
    if reference is None:
        reference = champion_reference(tracking_uri, EVALUATOR.registered)
    return load_evaluator(reference, tracking_uri, device)
