"""The standard text-to-motion evaluator (the one behind published HumanML3D / KIT-ML numbers).

Architecture (the "Co" variants of Guo et al.'s evaluator, ``networks/modules.py`` of
EricGuo5513/text-to-motion, copied unchanged as ``models/modules.py`` into T2M-GPT and MMM):

* movement encoder: two Conv1d(k=4, stride 2, padding 1) with Dropout(0.2) and LeakyReLU(0.2)
  over the D-4 non-contact feature dims (259 HumanML3D, 247 KIT-ML), then a per-step
  Linear(512, 512); time is downsampled by 4.
* motion encoder: Linear(512, 1024), bidirectional GRU(1024) with a learned initial state,
  packed by length // 4, both final states concatenated -> Linear, LayerNorm, LeakyReLU, Linear
  -> 512.
* text encoder: 300-d GloVe vectors plus Linear(15, 300) of a POS one-hot, Linear(300, 512),
  bidirectional GRU(512) with a learned initial state, packed by caption length (sos/eos
  included) -> Linear, LayerNorm, LeakyReLU, Linear -> 512.

Module attribute names and their order follow the published state dicts, key by key, so the
published weights load with ``strict=True``.

Files the user provides (nothing is downloaded or shipped here). Paths are those inside the
published downloads, relative to the folder the download scripts run in:

* ``checkpoints/t2m/text_mot_match/model/finest.tar`` (KIT-ML: ``checkpoints/kit/...``): read
  by :meth:`T2MEvaluator.load` from ``<evaluator_dir>/text_mot_match/model/finest.tar``, with
  ``evaluator_dir`` = ``checkpoints/t2m`` or ``checkpoints/kit``. Its top-level keys, as the
  evaluator's trainer saves them, are ``text_encoder``, ``motion_encoder``, ``movement_encoder``
  (the three state dicts the wrapper loads and the only ones used here), ``opt_text_encoder``,
  ``opt_motion_encoder`` (Adam states), ``epoch`` and ``iter``.
* ``glove/our_vab_data.npy``, ``glove/our_vab_words.pkl``, ``glove/our_vab_idx.pkl``: the word
  vectors, read from ``<glove_dir>`` by :class:`WordVectorizer`.
* the evaluator normalization ``checkpoints/t2m/VQVAEV3_CB1024_CMT_H1024_NRES3/meta/mean.npy``
  and ``std.npy`` (KIT-ML: ``checkpoints/kit/VQVAEV3_CB1024_CMT_H1024_NRES3/meta``): the folder
  T2M-GPT's and MMM's ``dataset/dataset_TM_eval.py`` normalize the evaluation data with; read by
  :func:`load_mean_std`. (The evaluator itself was trained with the statistics of
  ``checkpoints/t2m/Comp_v6_KLD01/meta`` resp. ``checkpoints/kit/Comp_v6_KLD005/meta``, see
  ``train_tex_mot_match.py`` of text-to-motion. MMM also commits a HumanML3D copy as
  ``exit/t2m-mean.npy`` / ``exit/t2m-std.npy``, used by its ``generate.py``.) For HumanML3D that
  std is the dataset Std.npy with the root (dims 0-3) and foot-contact (last 4) dims divided by
  feat_bias = 25 (ratios 24.9-25.25 against HumanML3D's Std.npy), the other dims within 0.4%.

Where they come from: in the T2M-GPT (Mael-zys/T2M-GPT) and MMM (exitudio/MMM) repositories,
``bash dataset/prepare/download_extractor.sh`` downloads ``t2m.zip`` and ``kit.zip`` and unzips
them into ``./checkpoints`` (their code then reads ``checkpoints/{t2m,kit}/text_mot_match``,
``.../Comp_v6_KLD005/opt.txt`` and ``.../VQVAEV3_CB1024_CMT_H1024_NRES3/meta`` from there), and
``bash dataset/prepare/download_glove.sh`` downloads ``glove.zip`` and unzips it into ``./glove``
(their code reads ``WordVectorizer('./glove', 'our_vab')``). The evaluator's own repository
(EricGuo5513/text-to-motion) links its model folders from its README ("Download Data &
Pre-trained Models"; ``checkpoints/t2m/text_mot_match`` is among them) and keeps
``glove/our_vab_*`` in the repository itself. The published wrapper takes its sizes from that
``Comp_v6_KLD005/opt.txt`` (unit_length 4, movement hidden/latent 512); this module has those
numbers built in and does not read it.

Differences from the published wrapper, none of which changes a number (checked against the
published modules, wrapper logic and eval-dataset caption code with shared random weights: the
embeddings agree exactly):

* ``embed_motions`` / ``embed_texts`` return embeddings in the order of their inputs (the
  text-to-motion wrapper returns them sorted by motion length; T2M-GPT/MMM's returns them in the
  batch order); sorting for packing happens inside.
* frames at or beyond a motion's length are set to zero and the time axis is brought to 196
  frames before the convolutions, so neither padding content nor the batch's padded size
  changes an embedding (the published pipeline pads every motion with zeros to 196 frames,
  which is exactly this).
* tokens the published code would reject (no ``/``, or several) are accepted: the part after the
  last ``/`` is the tag, none means OTHER; extra whitespace in a token string is ignored.

Inputs of ``embed_motions`` must already be in the evaluator's normalization; a model trained
with other statistics maps its outputs with :class:`EvaluatorNormalization`
(x_eval = (x * std + mean - mean_e) / std_e).
"""

from __future__ import annotations

import io
import pickle
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
import torch
from torch import nn
from torch.nn.utils.rnn import pack_padded_sequence

from mmm.checkpoints import CheckpointError
from mmm.data.arrays import load_array
from mmm.data.humanml3d import DataError

# --------------------------------------------------------------------------------------------
# Constants of the published evaluator
# --------------------------------------------------------------------------------------------

FEATURE_DIMS = {"humanml3d": 263, "kit": 251}
_DATASET_ALIASES = {
    "humanml3d": "humanml3d",
    "t2m": "humanml3d",
    "kit": "kit",
    "kit-ml": "kit",
    "kitml": "kit",
}
CONTACT_DIMS = 4
UNIT_LENGTH = 4
WORD_DIM = 300
MAX_TEXT_TOKENS = 20  # caption tokens kept; the sequence adds sos and eos
TEXT_SEQ_LEN = MAX_TEXT_TOKENS + 2
MAX_MOTION_LENGTH = 196  # frames the published pipeline pads every motion to (both datasets)
EMBED_DIM = 512
MOVEMENT_HIDDEN = 512
MOVEMENT_LATENT = 512
MOTION_HIDDEN = 1024
TEXT_HIDDEN = 512

POS_CLASSES = (
    "VERB", "NOUN", "DET", "ADP", "NUM", "AUX", "PRON", "ADJ", "ADV",
    "Loc_VIP", "Body_VIP", "Obj_VIP", "Act_VIP", "Desc_VIP", "OTHER",
)  # fmt: skip
POS_INDEX = {name: i for i, name in enumerate(POS_CLASSES)}

VIP_WORDS: dict[str, tuple[str, ...]] = {
    "Loc_VIP": (
        "left",
        "right",
        "clockwise",
        "counterclockwise",
        "anticlockwise",
        "forward",
        "back",
        "backward",
        "up",
        "down",
        "straight",
        "curve",
    ),
    "Body_VIP": (
        "arm",
        "chin",
        "foot",
        "feet",
        "face",
        "hand",
        "mouth",
        "leg",
        "waist",
        "eye",
        "knee",
        "shoulder",
        "thigh",
    ),
    "Obj_VIP": (
        "stair",
        "dumbbell",
        "chair",
        "window",
        "floor",
        "car",
        "ball",
        "handrail",
        "baseball",
        "basketball",
    ),
    "Act_VIP": (
        "walk",
        "run",
        "swing",
        "pick",
        "bring",
        "kick",
        "put",
        "squat",
        "throw",
        "hop",
        "dance",
        "jump",
        "turn",
        "stumble",
        "stop",
        "sit",
        "lift",
        "lower",
        "raise",
        "wash",
        "stand",
        "kneel",
        "stroll",
        "rub",
        "bend",
        "balance",
        "flap",
        "jog",
        "shuffle",
        "lean",
        "rotate",
        "spin",
        "spread",
        "climb",
    ),
    "Desc_VIP": (
        "slowly",
        "carefully",
        "fast",
        "careful",
        "slow",
        "quickly",
        "happy",
        "angry",
        "sad",
        "happily",
        "angrily",
        "sadly",
    ),
}
# first list wins, as in the published vectorizer (the lists do not overlap)
_VIP_CLASS: dict[str, str] = {}
for _cls, _words in VIP_WORDS.items():
    for _w in _words:
        _VIP_CLASS.setdefault(_w, _cls)

CHECKPOINT_RELPATH = Path("text_mot_match") / "model" / "finest.tar"
GLOVE_FILES = ("our_vab_data.npy", "our_vab_words.pkl", "our_vab_idx.pkl")
_COMPONENTS = ("movement_encoder", "motion_encoder", "text_encoder")

_WHERE_FROM = (
    "These files are not shipped or downloaded by this package: they come from the public "
    "release of the T2M evaluator of Guo et al. (github.com/EricGuo5513/text-to-motion), as "
    "redistributed by T2M-GPT (Mael-zys/T2M-GPT) and MMM (exitudio/MMM). In either of those two "
    "repositories, `bash dataset/prepare/download_extractor.sh` unzips t2m.zip and kit.zip into "
    "./checkpoints, which gives the evaluator weights `checkpoints/t2m/text_mot_match/model/"
    "finest.tar` (KIT-ML: `checkpoints/kit/text_mot_match/model/finest.tar`) and the evaluation "
    "normalization `checkpoints/t2m/VQVAEV3_CB1024_CMT_H1024_NRES3/meta/{mean,std}.npy`; "
    "`bash dataset/prepare/download_glove.sh` unzips glove.zip into ./glove, which gives "
    "`glove/our_vab_data.npy`, `glove/our_vab_words.pkl`, `glove/our_vab_idx.pkl`. "
    "Pass `checkpoints/t2m` (or `checkpoints/kit`), the folder that holds `text_mot_match/`, as "
    "evaluator_dir and the `glove` folder as glove_dir."
)


def canonical_dataset(dataset: str) -> str:
    key = str(dataset).lower()
    if key not in _DATASET_ALIASES:
        raise ValueError(f"unknown dataset {dataset!r} for the T2M evaluator: expected 'humanml3d' or 'kit'")
    return _DATASET_ALIASES[key]


# --------------------------------------------------------------------------------------------
# Errors and safe file readers
# --------------------------------------------------------------------------------------------


class EvaluatorFilesMissing(FileNotFoundError):
    """Raised when evaluator files the user must provide are absent; `missing` lists them."""

    def __init__(self, missing: Sequence[tuple[str, Path]]):
        self.missing = [(what, Path(p)) for what, p in missing]
        lines = [f"  - {what}: expected at {p}" for what, p in self.missing]
        super().__init__(
            f"the standard T2M evaluator needs {len(self.missing)} missing file(s):\n"
            + "\n".join(lines)
            + "\n"
            + _WHERE_FROM
        )

    def __str__(self) -> str:  # FileNotFoundError would otherwise print only errno-style text
        return self.args[0]


class EvaluatorCheckpointError(CheckpointError, RuntimeError):
    """The evaluator checkpoint could not be read or does not match the published layout (a
    CheckpointError: the CLI prints it and exits 2; a RuntimeError as it always was)."""


class _RestrictedUnpickler(pickle.Unpickler):
    """Unpickler that only builds lists, dicts, strings and ints: no code runs while loading."""

    _ALLOWED = frozenset(
        {("builtins", "list"), ("builtins", "dict"), ("builtins", "str"), ("builtins", "int")}
    )

    def find_class(self, module: str, name: str):
        if module == "__builtin__":  # Python 2 pickles
            module = "builtins"
        if (module, name) in self._ALLOWED:
            return super().find_class(module, name)
        raise pickle.UnpicklingError(
            f"refusing to load {module}.{name}: only builtins list/dict/str/int are allowed in "
            "vocabulary pickles"
        )


def restricted_pickle_load(path_or_bytes: str | Path | bytes):
    """Load a pickle holding only list/dict/str/int (and the literals pickle encodes natively)."""
    if isinstance(path_or_bytes, (bytes, bytearray)):
        return _RestrictedUnpickler(io.BytesIO(path_or_bytes)).load()
    with open(path_or_bytes, "rb") as f:
        return _RestrictedUnpickler(f).load()


def _read_vocabulary(path: Path, fix: str):
    """A GloVe vocabulary pickle through the restricted unpickler; any failure (a damaged file,
    a class outside list/dict/str/int) a DataError naming the file."""
    try:
        return restricted_pickle_load(path)
    except (
        pickle.UnpicklingError,
        EOFError,
        OSError,
        ValueError,
        TypeError,
        KeyError,
        IndexError,
        AttributeError,
        UnicodeDecodeError,
    ) as e:
        detail = str(e).strip().splitlines()[0][:200] if str(e).strip() else type(e).__name__
        raise DataError(path, f"not a readable vocabulary pickle ({detail})", fix) from None


def load_checkpoint_dict(path: str | Path) -> dict:
    """torch.load(weights_only=True) of an evaluator checkpoint, with a clear error otherwise."""
    path = Path(path)
    if not path.is_file():
        raise EvaluatorFilesMissing([("evaluator checkpoint", path)])
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as e:
        raise EvaluatorCheckpointError(
            f"{path} could not be loaded with torch.load(weights_only=True): it contains objects "
            "other than tensors and plain containers, and this package does not unpickle "
            "arbitrary objects (that could run code). Re-save just the state dicts, e.g. "
            "torch.save({k: ckpt[k] for k in ('text_encoder', 'movement_encoder', "
            f"'motion_encoder')}}, path) in a trusted session. Original error: {e}"
        ) from e
    except Exception as e:  # corrupt or not a torch file
        raise EvaluatorCheckpointError(f"could not read the evaluator checkpoint {path}: {e}") from e
    if not isinstance(ckpt, Mapping):
        raise EvaluatorCheckpointError(
            f"{path} holds a {type(ckpt).__name__}, expected a dict with the state dicts "
            f"{', '.join(_COMPONENTS)}"
        )
    return dict(ckpt)


# --------------------------------------------------------------------------------------------
# Word vectorizer
# --------------------------------------------------------------------------------------------


class WordVectorizer:
    """GloVe vector plus POS one-hot for `word/POS` tokens, as the published data code does it.

    A word in a VIP list takes that class, otherwise its POS tag when the tag is one of the 15
    class names (in real captions one of the first nine, spaCy's tags), else OTHER; a word outside
    the vocabulary becomes the 'unk' vector with class OTHER, whatever its tag. Words are looked up
    as written (no lower-casing, no lemmatization): HumanML3D / KIT-ML caption tokens already
    carry lower-case lemmas (`walk/VERB`).
    """

    def __init__(self, vectors: np.ndarray, words: Sequence[str], word2idx: Mapping[str, int]):
        vectors = np.asarray(vectors, dtype=np.float32)
        if vectors.ndim != 2:
            raise ValueError(f"word vectors must be (V, dim), got shape {vectors.shape}")
        self.dim = int(vectors.shape[1])
        self.word2vec: dict[str, np.ndarray] = {}
        for w in words:
            if w not in word2idx:
                raise ValueError(f"word {w!r} of the word list has no index in the index dict")
            i = int(word2idx[w])
            if not 0 <= i < len(vectors):
                raise ValueError(f"index {i} of word {w!r} is outside the {len(vectors)} vectors")
            self.word2vec[w] = vectors[i]
        if "unk" not in self.word2vec:
            raise ValueError("the word vocabulary has no 'unk' entry, which unknown words map to")

    @classmethod
    def load(cls, glove_dir: str | Path, prefix: str = "our_vab") -> "WordVectorizer":
        glove_dir = Path(glove_dir)
        paths = [
            glove_dir / f"{prefix}_data.npy",
            glove_dir / f"{prefix}_words.pkl",
            glove_dir / f"{prefix}_idx.pkl",
        ]
        missing = [(f"GloVe file {p.name}", p) for p in paths if not p.is_file()]
        if missing:
            raise EvaluatorFilesMissing(missing)
        return cls._from_paths(*paths)

    @classmethod
    def _from_paths(cls, data_path: Path, words_path: Path, idx_path: Path) -> "WordVectorizer":
        fix = "download the GloVe files again: " + _WHERE_FROM
        vectors = load_array(data_path, "GloVe word vectors", fix)
        words = _read_vocabulary(words_path, fix)
        word2idx = _read_vocabulary(idx_path, fix)
        if not isinstance(words, list) or not all(isinstance(w, str) for w in words):
            raise DataError(words_path, "must hold a list of words (str)", fix)
        if not isinstance(word2idx, dict):
            raise DataError(idx_path, "must hold a dict word -> index", fix)
        try:
            return cls(vectors, words, word2idx)
        except ValueError as e:
            raise DataError(data_path.parent, f"the GloVe files do not fit together ({e})", fix) from None

    @staticmethod
    def pos_class(word: str, pos: str) -> str:
        """The class of an in-vocabulary word: its VIP list first, then its tag when the tag is
        one of the 15 class names (the published lookup accepts every name of its enumerator,
        VIP names and OTHER included), else OTHER."""
        if word in _VIP_CLASS:
            return _VIP_CLASS[word]
        return pos if pos in POS_INDEX else "OTHER"

    def classify(self, token: str) -> tuple[str, str]:
        """`word/POS` -> (word used for the vector, class name)."""
        word, pos = _split_token(token)
        if word not in self.word2vec:
            return "unk", "OTHER"
        return word, self.pos_class(word, pos)

    def __getitem__(self, token: str) -> tuple[np.ndarray, np.ndarray]:
        word, cls = self.classify(token)
        onehot = np.zeros(len(POS_CLASSES), dtype=np.float32)
        onehot[POS_INDEX[cls]] = 1.0
        return self.word2vec[word], onehot

    def caption_tokens(self, tokens: Sequence[str] | str) -> tuple[list[str], int]:
        """The published layout: sos + at most 20 tokens + eos, then unk padding to 22.

        Returns the 22 tokens and the length (real tokens + 2)."""
        tokens = caption_token_list(tokens)[:MAX_TEXT_TOKENS]
        seq = ["sos/OTHER", *tokens, "eos/OTHER"]
        length = len(seq)
        seq += ["unk/OTHER"] * (TEXT_SEQ_LEN - length)
        return seq, length

    def encode(
        self, token_lists: Sequence[Sequence[str] | str]
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Batch of captions -> word vectors (B, 22, 300), POS one-hots (B, 22, 15), lengths (B,)."""
        B = len(token_lists)
        words = np.zeros((B, TEXT_SEQ_LEN, self.dim), dtype=np.float32)
        pos = np.zeros((B, TEXT_SEQ_LEN, len(POS_CLASSES)), dtype=np.float32)
        lengths = np.zeros(B, dtype=np.int64)
        for b, toks in enumerate(token_lists):
            seq, lengths[b] = self.caption_tokens(toks)
            for t, tok in enumerate(seq):
                words[b, t], pos[b, t] = self[tok]
        return torch.from_numpy(words), torch.from_numpy(pos), torch.from_numpy(lengths)


def _split_token(token: str) -> tuple[str, str]:
    if "/" not in token:
        return token, "OTHER"
    word, pos = token.rsplit("/", 1)
    return word, pos


def caption_token_list(tokens: Sequence[str] | str) -> list[str]:
    """Accept a list of `word/POS` strings, a space-separated token string, or a full dataset
    caption line `caption#tok tok ...#start#end` (its second field)."""
    if isinstance(tokens, str):
        text = tokens.split("#")[1] if "#" in tokens else tokens
        return text.split()
    return [str(t) for t in tokens]


# --------------------------------------------------------------------------------------------
# Networks (attribute names = the published state-dict keys)
# --------------------------------------------------------------------------------------------


class MovementConvEncoder(nn.Module):
    """(B, T, Din) -> (B, T // 4, 512): two stride-2 convolutions and a per-step linear."""

    def __init__(
        self, input_size: int, hidden_size: int = MOVEMENT_HIDDEN, output_size: int = MOVEMENT_LATENT
    ):
        super().__init__()
        self.main = nn.Sequential(
            nn.Conv1d(input_size, hidden_size, 4, 2, 1),
            nn.Dropout(0.2),
            nn.LeakyReLU(0.2),
            nn.Conv1d(hidden_size, output_size, 4, 2, 1),
            nn.Dropout(0.2),
            nn.LeakyReLU(0.2),
        )
        self.out_net = nn.Linear(output_size, output_size)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = self.main(x.transpose(1, 2)).transpose(1, 2)
        return self.out_net(h)


class _BiGRUCo(nn.Module):
    """input_emb -> packed bidirectional GRU from a learned state -> output_net on both finals."""

    def __init__(self, input_size: int, hidden_size: int, output_size: int, pos_size: int | None = None):
        super().__init__()
        self.hidden_size = hidden_size
        if pos_size is not None:  # text encoder: registered first, as in the published key order
            self.pos_emb = nn.Linear(pos_size, input_size)
        self.input_emb = nn.Linear(input_size, hidden_size)
        self.gru = nn.GRU(hidden_size, hidden_size, batch_first=True, bidirectional=True)
        self.output_net = nn.Sequential(
            nn.Linear(hidden_size * 2, hidden_size),
            nn.LayerNorm(hidden_size),
            nn.LeakyReLU(0.2),
            nn.Linear(hidden_size, output_size),
        )
        self.hidden = nn.Parameter(torch.randn(2, 1, hidden_size))

    def _encode(self, x: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
        """x (B, T, input) with lengths (B,) in any order; returns (B, output) in input order."""
        lengths = torch.as_tensor(lengths).to("cpu", torch.int64)
        if lengths.ndim != 1 or lengths.shape[0] != x.shape[0]:
            raise ValueError(f"lengths must be ({x.shape[0]},), got {tuple(lengths.shape)}")
        if bool((lengths < 1).any()) or int(lengths.max()) > x.shape[1]:
            raise ValueError(f"sequence lengths must lie in [1, {x.shape[1]}], got {lengths.tolist()}")
        # packing wants the batch sorted longest first; sort, run, then restore the input order
        order = torch.argsort(lengths, descending=True, stable=True)
        inverse = torch.empty_like(order)
        inverse[order] = torch.arange(order.numel())
        emb = self.input_emb(x[order.to(x.device)])
        packed = pack_padded_sequence(emb, lengths[order], batch_first=True, enforce_sorted=True)
        h0 = self.hidden.repeat(1, x.shape[0], 1)
        _, last = self.gru(packed, h0)
        out = self.output_net(torch.cat([last[0], last[1]], dim=-1))
        return out[inverse.to(out.device)]


class MotionEncoderBiGRUCo(_BiGRUCo):
    def __init__(
        self,
        input_size: int = MOVEMENT_LATENT,
        hidden_size: int = MOTION_HIDDEN,
        output_size: int = EMBED_DIM,
    ):
        super().__init__(input_size, hidden_size, output_size)

    def forward(self, movements: torch.Tensor, unit_lengths: torch.Tensor) -> torch.Tensor:
        return self._encode(movements, unit_lengths)


class TextEncoderBiGRUCo(_BiGRUCo):
    def __init__(
        self,
        word_size: int = WORD_DIM,
        pos_size: int = len(POS_CLASSES),
        hidden_size: int = TEXT_HIDDEN,
        output_size: int = EMBED_DIM,
    ):
        super().__init__(word_size, hidden_size, output_size, pos_size=pos_size)

    def forward(
        self, word_embs: torch.Tensor, pos_onehot: torch.Tensor, lengths: torch.Tensor
    ) -> torch.Tensor:
        return self._encode(word_embs + self.pos_emb(pos_onehot), lengths)


# --------------------------------------------------------------------------------------------
# The evaluator
# --------------------------------------------------------------------------------------------


class T2MEvaluator(nn.Module):
    """The standard text-to-motion evaluator (frozen, always in eval mode).

    `T2MEvaluator(dataset)` builds it with random weights (tests, shape checks);
    `T2MEvaluator.load(evaluator_dir, glove_dir, dataset)` loads the user-provided files.
    """

    def __init__(self, dataset: str = "humanml3d", word_vectorizer: WordVectorizer | None = None):
        super().__init__()
        self.dataset = canonical_dataset(dataset)
        self.feature_dim = FEATURE_DIMS[self.dataset]
        self.unit_length = UNIT_LENGTH
        self.embed_dim = EMBED_DIM
        self.movement_encoder = MovementConvEncoder(self.feature_dim - CONTACT_DIMS)
        self.motion_encoder = MotionEncoderBiGRUCo()
        self.text_encoder = TextEncoderBiGRUCo()
        self.word_vectorizer = word_vectorizer
        self.requires_grad_(False)
        self.eval()

    def train(self, mode: bool = True) -> "T2MEvaluator":
        # A frozen yardstick: dropout stays off even when a parent module switches to training.
        return super().train(False)

    @property
    def device(self) -> torch.device:
        return self.motion_encoder.hidden.device

    # ---- loading --------------------------------------------------------------------------

    @staticmethod
    def expected_files(evaluator_dir: str | Path, glove_dir: str | Path) -> list[tuple[str, Path]]:
        g = Path(glove_dir)
        return [("evaluator checkpoint", Path(evaluator_dir) / CHECKPOINT_RELPATH)] + [
            (f"GloVe file {name}", g / name) for name in GLOVE_FILES
        ]

    @classmethod
    def load(
        cls,
        evaluator_dir: str | Path,
        glove_dir: str | Path,
        dataset: str = "humanml3d",
        map_location: str | torch.device = "cpu",
    ) -> "T2MEvaluator":
        """Load `<evaluator_dir>/text_mot_match/model/finest.tar` and `<glove_dir>/our_vab_*`.

        Raises EvaluatorFilesMissing listing every absent file, EvaluatorCheckpointError when
        the checkpoint cannot be read safely or its state dicts do not match strictly."""
        files = cls.expected_files(evaluator_dir, glove_dir)
        missing = [(what, p) for what, p in files if not p.is_file()]
        if missing:
            raise EvaluatorFilesMissing(missing)
        vectorizer = WordVectorizer._from_paths(*(p for _, p in files[1:]))
        model = cls(dataset, word_vectorizer=vectorizer)
        model.load_checkpoint(files[0][1])
        return model.to(map_location)

    def load_checkpoint(self, path_or_dict: str | Path | Mapping) -> "T2MEvaluator":
        """Load the three state dicts of a finest.tar-style checkpoint with strict matching."""
        if isinstance(path_or_dict, Mapping):
            ckpt, source = dict(path_or_dict), "checkpoint dict"
        else:
            ckpt, source = load_checkpoint_dict(path_or_dict), str(path_or_dict)
        problems: list[str] = []
        absent = [c for c in _COMPONENTS if not isinstance(ckpt.get(c), Mapping)]
        if absent:
            raise EvaluatorCheckpointError(
                f"{source} lacks the state dict(s) {', '.join(absent)} (found keys: "
                f"{sorted(map(str, ckpt))}); expected the published text_mot_match/model/finest.tar layout"
            )
        for name in _COMPONENTS:
            problems += _state_dict_problems(name, getattr(self, name), ckpt[name])
        if problems:
            raise EvaluatorCheckpointError(
                f"{source} does not match the {self.dataset} T2M evaluator "
                f"(feature dim {self.feature_dim}; a KIT-ML checkpoint has 247 movement input "
                "channels, a HumanML3D one 259):\n  " + "\n  ".join(problems)
            )
        for name in _COMPONENTS:
            sd = {k: v.to(torch.float32) if v.is_floating_point() else v for k, v in ckpt[name].items()}
            getattr(self, name).load_state_dict(sd, strict=True)
        return self

    # ---- embedding ------------------------------------------------------------------------

    @torch.no_grad()
    def encode_texts(self, word_embs: torch.Tensor, pos_onehot: torch.Tensor, lengths) -> torch.Tensor:
        """Word vectors (B, L, 300), POS one-hots (B, L, 15), lengths (B,) -> (B, 512)."""
        dev = self.device
        return self.text_encoder(word_embs.to(dev, torch.float32), pos_onehot.to(dev, torch.float32), lengths)

    @torch.no_grad()
    def embed_texts(self, token_lists: Sequence[Sequence[str] | str]) -> torch.Tensor:
        """Captions as `word/POS` token lists (or token strings / caption lines) -> (B, 512)."""
        if self.word_vectorizer is None:
            raise RuntimeError(
                "this T2MEvaluator has no word vectorizer: build it with T2MEvaluator.load(...) or "
                "pass word_vectorizer=WordVectorizer.load(glove_dir)"
            )
        words, pos, lengths = self.word_vectorizer.encode(token_lists)
        return self.encode_texts(words, pos, lengths)

    @torch.no_grad()
    def embed_motions(self, features: torch.Tensor, lengths) -> torch.Tensor:
        """Features (B, T, D) in the evaluator's normalization, lengths (B,) in frames -> (B, 512).

        Frames at or beyond a length are zeroed and the time axis is zero-padded (or cut) to 196
        frames, exactly as the published pipeline feeds the evaluator, so the result does not
        depend on how the caller padded the batch. Each motion is encoded over length // 4 steps,
        so lengths must be at least 4 (lengths over 196 widen the window to the longest)."""
        features = torch.as_tensor(features)
        if features.ndim != 3 or features.shape[-1] != self.feature_dim:
            raise ValueError(
                f"expected features (B, T, {self.feature_dim}) for the {self.dataset} evaluator, "
                f"got {tuple(features.shape)}"
            )
        lengths = torch.as_tensor(lengths).to("cpu", torch.int64).reshape(-1)
        B, T, _ = features.shape
        if lengths.shape[0] != B:
            raise ValueError(f"got {lengths.shape[0]} lengths for {B} motions")
        if bool((lengths < self.unit_length).any()) or int(lengths.max()) > T:
            raise ValueError(f"motion lengths must lie in [{self.unit_length}, {T}], got {lengths.tolist()}")
        x = features.to(self.device, torch.float32)[..., : self.feature_dim - CONTACT_DIMS]
        valid = torch.arange(T, device=x.device)[None, :] < lengths.to(x.device)[:, None]
        x = torch.where(valid[..., None], x, x.new_zeros(()))  # NaN padding included
        # The published pipeline always feeds 196 frames, zero-padded after the length. The last
        # kept step's receptive field reaches up to 3 frames past the length, and a padded zero
        # frame (conv bias + activation in layer 1) differs from the second conv's own zero
        # padding, so the window length matters: use exactly the published one.
        window = max(MAX_MOTION_LENGTH, int(lengths.max()))
        if T < window:
            x = torch.cat([x, x.new_zeros(B, window - T, x.shape[-1])], dim=1)
        else:
            x = x[:, :window]
        movements = self.movement_encoder(x)
        return self.motion_encoder(movements, lengths // self.unit_length)

    @torch.no_grad()
    def forward(self, token_lists, features, lengths) -> tuple[torch.Tensor, torch.Tensor]:
        """(text embeddings, motion embeddings), both (B, 512) in input order."""
        return self.embed_texts(token_lists), self.embed_motions(features, lengths)


def _state_dict_problems(name: str, module: nn.Module, sd: Mapping) -> list[str]:
    own = module.state_dict()
    problems = []
    missing = [k for k in own if k not in sd]
    unexpected = [k for k in sd if k not in own]
    if missing:
        problems.append(f"{name}: missing keys {missing}")
    if unexpected:
        problems.append(f"{name}: unexpected keys {unexpected}")
    for k, v in own.items():
        if k in sd:
            got = sd[k]
            if not isinstance(got, torch.Tensor):
                problems.append(f"{name}.{k}: expected a tensor, got {type(got).__name__}")
            elif tuple(got.shape) != tuple(v.shape):
                problems.append(
                    f"{name}.{k}: shape {tuple(got.shape)} in the checkpoint, {tuple(v.shape)} expected"
                )
    return problems


# --------------------------------------------------------------------------------------------
# Normalization mapping
# --------------------------------------------------------------------------------------------


def load_mean_std(directory: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """mean.npy/std.npy (the evaluator-norm naming) or Mean.npy/Std.npy (the dataset naming)."""
    directory = Path(directory)
    for m, s in (("mean.npy", "std.npy"), ("Mean.npy", "Std.npy")):
        if (directory / m).is_file() and (directory / s).is_file():
            fix = f"restore the evaluator's statistics in {directory}"
            mean = load_array(directory / m, "evaluator normalization mean", fix).astype(np.float64)
            std = load_array(directory / s, "evaluator normalization std", fix).astype(np.float64)
            return mean, std
    raise FileNotFoundError(
        f"no normalization statistics in {directory}: expected mean.npy and std.npy (or Mean.npy "
        "and Std.npy). The standard T2M evaluator's statistics ship with the evaluation release: "
        "checkpoints/t2m/VQVAEV3_CB1024_CMT_H1024_NRES3/meta/mean.npy and std.npy (KIT-ML: "
        "checkpoints/kit/...), unzipped by dataset/prepare/download_extractor.sh of T2M-GPT / MMM"
    )


class EvaluatorNormalization:
    """Maps features normalized with training statistics to the evaluator's normalization.

    to_evaluator(x) = (x * std + mean - mean_e) / std_e, from_evaluator is its inverse. Works on
    numpy arrays and torch tensors (dtype and device kept), over the last axis."""

    def __init__(self, train_mean, train_std, eval_mean, eval_std):
        arrs = [
            np.asarray(a, dtype=np.float64).reshape(-1) for a in (train_mean, train_std, eval_mean, eval_std)
        ]
        if len({a.shape[0] for a in arrs}) != 1:
            raise ValueError(f"statistics differ in size: {[a.shape[0] for a in arrs]}")
        self.train_mean, self.train_std, self.eval_mean, self.eval_std = arrs
        if not (np.all(self.train_std > 0) and np.all(self.eval_std > 0)):
            raise ValueError("standard deviations must be positive")
        self.scale = self.train_std / self.eval_std
        self.shift = (self.train_mean - self.eval_mean) / self.eval_std
        self.dim = self.scale.shape[0]

    @classmethod
    def from_dirs(cls, train_stats_dir: str | Path, eval_stats_dir: str | Path) -> "EvaluatorNormalization":
        m, s = load_mean_std(train_stats_dir)
        me, se = load_mean_std(eval_stats_dir)
        return cls(m, s, me, se)

    def _coeffs(self, x):
        if x.shape[-1] != self.dim:
            raise ValueError(f"expected features with last dim {self.dim}, got {tuple(x.shape)}")
        if isinstance(x, torch.Tensor):
            dt = x.dtype if x.is_floating_point() else torch.float32
            return torch.as_tensor(self.scale, dtype=dt, device=x.device), torch.as_tensor(
                self.shift, dtype=dt, device=x.device
            )
        dt = x.dtype if np.issubdtype(np.asarray(x).dtype, np.floating) else np.float64
        return self.scale.astype(dt), self.shift.astype(dt)

    def to_evaluator(self, x):
        scale, shift = self._coeffs(x)
        return x * scale + shift

    def from_evaluator(self, x_eval):
        scale, shift = self._coeffs(x_eval)
        return (x_eval - shift) / scale


__all__ = [
    "EvaluatorCheckpointError",
    "EvaluatorFilesMissing",
    "EvaluatorNormalization",
    "MotionEncoderBiGRUCo",
    "MovementConvEncoder",
    "POS_CLASSES",
    "T2MEvaluator",
    "TextEncoderBiGRUCo",
    "VIP_WORDS",
    "WordVectorizer",
    "load_checkpoint_dict",
    "load_mean_std",
    "restricted_pickle_load",
]
