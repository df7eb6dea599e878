"""LightningDataModules over a dataset folder in the HumanML3D layout, configured by conf/data/*.yaml."""

from __future__ import annotations

import logging
import re
from pathlib import Path

import lightning as L
from lightning.pytorch.utilities import rank_zero_info, rank_zero_only
from torch.utils.data import DataLoader, Dataset

from mmm.data.configs import DataConfig, OversampleConfig
from mmm.data.datasets import (
    MotionClipDataset,
    MotionWindowDataset,
    TextMotionDataset,
    TokenBatchCollator,
    TokenTextDataset,
    collate_motions,
)
from mmm.data.humanml3d import DataError, LoadReport, load_clips, load_stats
from mmm.data.normalization import tokenizer_statistics
from mmm.data.resumable import ResumableDataLoader
from mmm.data.synthetic.generate import check_synthesis, generate_dataset
from mmm.data.tokens import TokenCache, token_cache_folder, tokenize_dataset
from mmm.fingerprint import dataset_fingerprint

log = logging.getLogger(__name__)


def oversample_items(items: list, cfg: OversampleConfig, where: str = "data") -> list:
    """A new list: `items` with each item that has a caption matching `cfg.pattern` repeated
    `cfg.factor` times where it stands (an epoch is then one permutation of the longer list, so the
    sharded, resumable sampler needs no change). Logs how many matched."""
    if not cfg.pattern:
        return items
    try:
        pattern = re.compile(cfg.pattern, re.IGNORECASE)
    except re.error as err:
        raise ValueError(
            f"data.oversample.pattern={cfg.pattern!r} is not a regular expression ({err}); "
            "fix it, or set data.oversample.pattern='' to turn oversampling off"
        ) from None
    if isinstance(cfg.factor, bool) or not isinstance(cfg.factor, int) or cfg.factor < 1:
        raise ValueError(
            f"data.oversample.factor={cfg.factor!r} must be a whole number of at least 1 (1: no oversampling)"
        )
    out, matched = [], 0
    for item in items:
        hit = any(pattern.search(c.text) for c in item.captions)
        matched += hit
        out.extend([item] * (cfg.factor if hit else 1))
    if not matched:
        _warn(
            f"{where}: none of the {len(items)} training items has a caption matching "
            f"data.oversample.pattern={cfg.pattern!r}, so none is oversampled: check the pattern"
        )
    else:
        rank_zero_info(
            f"{where}: {matched} of {len(items)} training items have a caption matching "
            f"data.oversample.pattern={cfg.pattern!r}; each is drawn {cfg.factor} times per epoch "
            f"({len(out)} draws per epoch)"
        )
    return out


def _warn(text: str) -> None:
    """A warning about the data, on rank 0, as a log line (a Python warning would print this
    file's path and source line with it)."""
    if rank_zero_only.rank == 0:
        log.warning(text)


def _log_report(what: str, report: LoadReport) -> None:
    """What a load kept and, as a warning, what it left out."""
    text = f"{what}: {report.summary()}"
    if report.skipped:
        _warn(text)
    else:
        rank_zero_info(text)


class _DatasetFolder(L.LightningDataModule):
    """Loaders shard across ranks and resume mid-epoch by themselves: train with
    Trainer(use_distributed_sampler=False)."""

    def __init__(self, cfg: DataConfig, seed: int = 0):
        super().__init__()
        self.cfg, self.seed = cfg, seed
        self.root = Path(cfg.root)
        self.mean = self.std = None
        self.reports: dict[str, LoadReport] = {}
        self.datasets: dict[str, Dataset] = {}

    def prepare_data(self) -> None:
        # Runs on one process per node only; the datasets are built in setup() on every rank.
        synth = self.cfg.synthesize
        if self.root.exists():
            if synth is not None:
                check_synthesis(
                    self.root,
                    synth.num_clips,
                    synth.seed,
                    synth.train_paraphrases,
                    synth.extra_train_clips,
                    synth.extra_composite_fraction,
                )
            return
        if synth is None:
            raise DataError(
                self.root,
                "dataset folder does not exist",
                "point data.root at a dataset in the HumanML3D layout",
            )

        rank_zero_info(
            f"{self.root} is missing: generating the synthetic dataset ({synth.num_clips} clips and "
            f"{synth.extra_train_clips} more for training ({synth.extra_composite_fraction:.2f} of them two "
            f"actions), seed {synth.seed}, {synth.train_paraphrases} "
            "captions per training clip)"
        )
        generate_dataset(
            self.root,
            num_clips=synth.num_clips,
            seed=synth.seed,
            train_paraphrases=synth.train_paraphrases,
            extra_train_clips=synth.extra_train_clips,
            extra_composite_fraction=synth.extra_composite_fraction,
        )

    def _stats(self) -> None:
        if self.mean is None:
            self.mean, self.std = load_stats(self.root, self.cfg.feature_dim)

    def _loader(self, dataset, shuffle: bool, **kwargs) -> DataLoader:
        return ResumableDataLoader(
            dataset,
            batch_size=self.cfg.batch_size,
            shuffle=shuffle,
            seed=self.seed,
            drop_last=shuffle,
            num_workers=self.cfg.num_workers,
            persistent_workers=self.cfg.num_workers > 0,
            **kwargs,
        )


class TokenizerDataModule(_DatasetFolder):
    """Stage 1: training batches of `window`-frame windows (B, window, D); validation on whole
    clips, padded: {"motion" (B, T, D), "lengths" (B,), "names"}. Normalized with the statistics
    `normalization` chooses (mmm.data.normalization; the dataset's Mean/Std when None).
    start_windows: the share of the training windows that are clip starts once the decoder
    refinement switches them on (MotionWindowDataset)."""

    def __init__(self, cfg: DataConfig, seed: int = 0, normalization=None, start_windows: float = 0.0):
        super().__init__(cfg, seed)
        self.normalization = normalization
        self.start_windows = start_windows

    def _stats(self) -> None:
        if self.mean is None and self.normalization is not None:
            self.mean, self.std = tokenizer_statistics(self.normalization, self.root, self.cfg.feature_dim)
        super()._stats()

    def setup(self, stage: str | None = None) -> None:
        # train_stage1 sets up before the fit (the module is built with the statistics, and a
        # dataset it cannot use fails before a run is opened); the fit's own call finds it done,
        # so each split is read and reported once.
        if self.datasets:
            return
        self._stats()
        for split in ("train", "val"):
            clips, report = load_clips(
                self.root,
                split,
                feature_dim=self.cfg.feature_dim,
                min_length=self.cfg.window,
                on_invalid=self.cfg.on_invalid,
            )
            self.reports[split] = report
            _log_report(f"{self.cfg.name} {split} clips", report)
            if split == "train":
                self.datasets[split] = MotionWindowDataset(
                    list(clips.values()), self.mean, self.std, self.cfg.window, self.start_windows
                )
            else:
                self.datasets[split] = MotionClipDataset(
                    clips,
                    self.mean,
                    self.std,
                    max_length=self.cfg.max_length,
                    unit_length=self.cfg.unit_length,
                )

    def train_dataloader(self) -> DataLoader:
        return self._loader(self.datasets["train"], shuffle=True)

    def val_dataloader(self) -> DataLoader:
        return self._loader(self.datasets["val"], shuffle=False, collate_fn=collate_motions)


class TextMotionDataModule(_DatasetFolder):
    """Stage 2 and evaluation: captioned motions, padded batches with lengths."""

    def setup(self, stage: str | None = None) -> None:
        self._stats()
        self.datasets = {}
        for split in ("train", "val", "test"):
            if split == "test" and stage == "fit":
                continue
            items, report = self.cfg.items(split, self.root)
            self.reports[split] = report
            _log_report(f"{self.cfg.name} {split} items", report)
            self.datasets[split] = TextMotionDataset(
                items,
                self.mean,
                self.std,
                max_length=self.cfg.max_length,
                unit_length=self.cfg.unit_length,
                random_crop=split == "train",
            )

    def train_dataloader(self) -> DataLoader:
        return self._loader(self.datasets["train"], shuffle=True, collate_fn=collate_motions)

    def val_dataloader(self) -> DataLoader:
        return self._loader(self.datasets["val"], shuffle=False, collate_fn=collate_motions)

    def test_dataloader(self) -> DataLoader:
        return self._loader(self.datasets["test"], shuffle=False, collate_fn=collate_motions)


class TokenTextDataModule(_DatasetFolder):
    """Stage 2: cached motion tokens with cached caption embeddings, batches from TokenBatchCollator.

    prepare_data (one process per node) synthesizes the dataset if configured, tokenizes the
    TOKEN_SPLITS with the stage-1 model (cached by tokenizer identity and data fingerprint) and
    caches the text embeddings of every caption; setup only reads the caches.
    """

    # The splits stage 2 and the length estimator read; the test motions are never tokenized for
    # them (on the synthetic default, 450 of 3,000 motions of the code search).
    TOKEN_SPLITS = ("train", "val")

    def __init__(
        self,
        cfg: DataConfig,
        seed: int,
        tokenizer,
        tokenizer_identity: str,
        text_encoder,
        caption_cache,
        token_cache_dir: str,
        max_tokens: int = 50,
        encoding=None,
    ):
        super().__init__(cfg, seed)
        self.tokenizer, self.tokenizer_identity = tokenizer, tokenizer_identity
        self.encoding = encoding  # the CodeSearchConfig of the tokens; None: the tokenizer's own
        self.text_encoder, self.caption_cache = text_encoder, caption_cache
        self.token_cache_dir, self.max_tokens = token_cache_dir, max_tokens
        self.tokens = None
        self.data_fingerprint: str | None = None
        self._loaded: dict[str, tuple] = {}

    def _items(self, split: str):
        # prepare_data reads every split for its captions and setup reads train/val again: on one
        # process that is the same dataset, read once (30k motions: seconds per read).
        if split not in self._loaded:
            self._loaded[split] = self.cfg.items(split, self.root)
        items, report = self._loaded[split]
        self.reports[split] = report
        return items, report

    def __getstate__(self):
        # ddp_spawn pickles the datamodule after prepare_data: each process reads the items itself.
        state = self.__dict__.copy()
        state["_loaded"] = {}
        return state

    def _token_folder(self):
        self.data_fingerprint = self.data_fingerprint or dataset_fingerprint(self.root)
        return token_cache_folder(
            self.token_cache_dir,
            self.tokenizer_identity,
            self.data_fingerprint,
            (self.encoding or self.tokenizer.encode_cfg).label,
        )

    def prepare_data(self) -> None:
        if getattr(self, "_prepared", False):  # Lightning calls it again inside fit
            return
        super().prepare_data()
        if self.tokenizer.tokenizer.feature_dim != self.cfg.feature_dim:
            raise DataError(
                self.root,
                f"the stage-1 model reads {self.tokenizer.tokenizer.feature_dim}-d features but data "
                f"{self.cfg.name!r} has {self.cfg.feature_dim}",
                "use a stage-1 model trained on this dataset (stage1=...)",
            )
        self.tokens = tokenize_dataset(
            self.tokenizer,
            self.root,
            self._token_folder(),
            splits=self.TOKEN_SPLITS,
            meta={"tokenizer": self.tokenizer_identity, "data": self.data_fingerprint},
            encoding=self.encoding,
        )
        captions = set()
        for split in ("train", "val", "test"):
            if (self.root / f"{split}.txt").exists():
                items, _ = self._items(split)
                captions.update(c.text for item in items for c in item.captions)
        counts = self.caption_cache.build(self.text_encoder, sorted(captions))
        message = (
            f"caption embeddings ({self.text_encoder.identity}): {counts['cached'] + counts['added']} "
            f"captions, {counts['added']} newly encoded"
        )
        if counts.get("truncated"):
            message += f"; {counts['truncated']} captions longer than the encoder's limit were truncated"
            _warn(message)
        else:
            rank_zero_info(message)
        self._prepared = True

    def setup(self, stage: str | None = None) -> None:
        self.tokens = self.tokens or TokenCache(self._token_folder())
        # END/PAD ids are K of the codebook; a part-aware tokenizer's two codebooks share one size.
        sizes = {q.num_codes for q in self.tokenizer.quantizers.values()}
        if len(sizes) != 1:
            raise ValueError(
                f"the stage-1 model's codebooks have different sizes {sorted(sizes)}; stage 2 needs one"
            )
        self.collate = TokenBatchCollator(self.caption_cache, sizes.pop(), self.max_tokens)
        self.datasets = {}
        for split in self.TOKEN_SPLITS:
            items, report = self._items(split)
            _log_report(f"{self.cfg.name} {split} items", report)
            if split == "train":
                items = oversample_items(items, self.cfg.oversample, str(self.root))
            self.datasets[split] = TokenTextDataset(
                items,
                self.tokens,
                unit_length=self.cfg.unit_length,
                max_codes=self.max_tokens - 1,
                seed=self.seed,
                augment=split == "train",
            )

    def train_dataloader(self) -> DataLoader:
        return self._loader(self.datasets["train"], shuffle=True, collate_fn=self.collate)

    def val_dataloader(self) -> DataLoader:
        return self._loader(self.datasets["val"], shuffle=False, collate_fn=self.collate)
