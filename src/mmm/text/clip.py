"""CLIP ViT-B/32 text tower (the paper's text encoder), native, loading weights from local files.

open_clip cannot be imported on machines without torchvision, so the text half of CLIP is
implemented here with the exact parameter names of open_clip / OpenAI CLIP, and the byte-level
BPE tokenizer reads the standard vocabulary file `bpe_simple_vocab_16e6.txt.gz`.

Nothing is ever downloaded: the weights and the vocabulary are files the user provides.
- weights: an open_clip or OpenAI CLIP ViT-B/32 checkpoint (`open_clip_pytorch_model.bin`,
  `open_clip_model.safetensors`, OpenAI's TorchScript `ViT-B-32.pt`, or any state dict saved
  with torch.save); the `visual.*` keys are ignored.
- vocab: `bpe_simple_vocab_16e6.txt.gz`, shipped inside the open_clip package
  (open_clip/bpe_simple_vocab_16e6.txt.gz) and the OpenAI CLIP repository
  (clip/bpe_simple_vocab_16e6.txt.gz). Found automatically when such a package is installed.

Sentence = ln_final at the end-of-text token @ text_projection (B, 512);
words = ln_final output at all 77 positions, before the projection (B, 77, 512).

Options that reproduce the released MMM model (OpenAI CLIP loaded on a GPU, as its training
script does) or depart from it:
- precision="float16" (default): OpenAI's dtype flow: Linear, attention and text_projection
  weights in float16, embeddings and LayerNorm parameters in float32, LayerNorm computed in
  float32 and cast back, everything else in float16 (also on the CPU). "float32": all float32.
- words="eot" (default): mask True up to and including the end-of-text token, later positions
  zeroed. "all": all 77 positions are words (mask all True, nothing zeroed), which is what the
  released transformer attends to.
Text is cleaned as OpenAI's tokenizer does, with ftfy (required: ids differ without it).
"""

from __future__ import annotations

import gzip
import hashlib
import html
import importlib.util
import math
import pickle
import zipfile
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Mapping

import torch
import torch.nn as nn
import torch.nn.functional as F

from .base import TextEmbedding, TextEncoder, state_dict_digest
from .torchscript import read_torchscript_tensors

VOCAB_FILENAME = "bpe_simple_vocab_16e6.txt.gz"
WEIGHTS_HINT = (
    "the open_clip ViT-B-32 weights (e.g. open_clip_pytorch_model.bin or open_clip_model.safetensors "
    "from the laion/CLIP-ViT-B-32-* or timm/vit_base_patch32_clip_224.openai model repositories) "
    "or OpenAI's TorchScript archive ViT-B-32.pt; download it on a machine with network access "
    "and pass its path: build_text_encoder('clip', weights=PATH, vocab=PATH)"
)
VOCAB_HINT = (
    f"the CLIP BPE vocabulary {VOCAB_FILENAME}, shipped in the open_clip package "
    f"(open_clip/{VOCAB_FILENAME}) and in OpenAI's CLIP repository (clip/{VOCAB_FILENAME}); "
    "pass its path: build_text_encoder('clip', weights=PATH, vocab=PATH)"
)
PRECISIONS = ("float16", "float32")
WORD_MODES = ("eot", "all")


# --------------------------------------------------------------------------------------------
# Tokenizer
# --------------------------------------------------------------------------------------------


@lru_cache()
def bytes_to_unicode() -> dict[int, str]:
    """Map every byte to a printable unicode character (printable latin-1 bytes map to themselves,
    the others to 256, 257, ...), so BPE runs on strings without whitespace/control characters."""
    keep = (
        list(range(ord("!"), ord("~") + 1))
        + list(range(ord("¡"), ord("¬") + 1))
        + list(range(ord("®"), ord("ÿ") + 1))
    )
    chars = list(keep)
    shift = 0
    for b in range(256):
        if b not in keep:
            keep.append(b)
            chars.append(256 + shift)
            shift += 1
    return {b: chr(c) for b, c in zip(keep, chars)}


def _require_ftfy():
    try:
        import ftfy  # optional dependency until a CLIP encoder is built
    except ImportError as e:
        raise ImportError(
            "the CLIP tokenizer needs the 'ftfy' package (OpenAI's tokenizer cleans every text with it; "
            "without it curly quotes, accents, ligatures and full-width text get other token ids): pip "
            "install ftfy"
        ) from e
    return ftfy


def _clean(text: str, fix_text) -> str:
    """OpenAI's clean-up: ftfy, HTML entities unescaped twice, whitespace collapsed, lower case."""
    text = html.unescape(html.unescape(fix_text(text))).strip()
    return " ".join(text.split()).lower()


class CLIPTokenizer:
    """CLIP's byte-level BPE: vocabulary = 256 bytes, 256 bytes + '</w>', one token per merge,
    then <|startoftext|> and <|endoftext|> (49408 entries for the standard file)."""

    SOT = "<|startoftext|>"
    EOT = "<|endoftext|>"
    MAX_MERGES = 49152 - 256 - 2  # the standard file holds more lines than CLIP uses
    cleanup = "ftfy"  # part of the encoder identity

    def __init__(self, vocab_path: str | Path, context_length: int = 77):
        self._fix_text = _require_ftfy().fix_text
        try:
            import regex  # optional dependency (the clip extra)
        except ImportError as e:
            raise ImportError("the CLIP tokenizer needs the 'regex' package: pip install regex") from e
        vocab_path = Path(vocab_path)
        if not vocab_path.is_file():
            raise FileNotFoundError(f"CLIP vocabulary file not found: {vocab_path}; expected {VOCAB_HINT}")
        raw = vocab_path.read_bytes()
        try:
            lines = gzip.decompress(raw).decode("utf-8").split("\n")
        except (OSError, UnicodeDecodeError) as e:
            raise ValueError(
                f"{vocab_path} is not a gzip-compressed CLIP merges file; expected {VOCAB_HINT}"
            ) from e
        merges = []
        for line in lines[1 : 1 + self.MAX_MERGES]:  # line 0 is the '#version' header
            parts = line.split()
            if not parts:
                continue
            if len(parts) != 2:
                raise ValueError(f"{vocab_path}: malformed merge line {line!r}; expected {VOCAB_HINT}")
            merges.append((parts[0], parts[1]))

        self.vocab_sha256 = hashlib.sha256(raw).hexdigest()
        self.context_length = context_length
        self.byte_encoder = bytes_to_unicode()
        self.byte_decoder = {c: b for b, c in self.byte_encoder.items()}
        vocab = list(self.byte_encoder.values())
        vocab += [c + "</w>" for c in vocab]
        vocab += ["".join(m) for m in merges]
        vocab += [self.SOT, self.EOT]
        self.encoder = {tok: i for i, tok in enumerate(vocab)}
        self.decoder = {i: tok for tok, i in self.encoder.items()}
        self.bpe_ranks = {m: i for i, m in enumerate(merges)}
        self.sot_token = self.encoder[self.SOT]
        self.eot_token = self.encoder[self.EOT]
        self.vocab_size = len(vocab)
        self._cache = {self.SOT: self.SOT, self.EOT: self.EOT}
        self._pattern = regex.compile(
            r"""<\|startoftext\|>|<\|endoftext\|>|'s|'t|'re|'ve|'m|'ll|'d|[\p{L}]+|[\p{N}]|[^\s\p{L}\p{N}]+""",
            regex.IGNORECASE,
        )

    def bpe(self, token: str) -> str:
        """One pre-token (byte-encoded) -> its BPE pieces joined by spaces; the last ends in '</w>'."""
        if token in self._cache:
            return self._cache[token]
        word = list(token[:-1]) + [token[-1] + "</w>"]
        while len(word) > 1:
            pairs = {(word[i], word[i + 1]) for i in range(len(word) - 1)}
            best = min(pairs, key=lambda p: self.bpe_ranks.get(p, math.inf))
            if best not in self.bpe_ranks:
                break
            merged, i = [], 0
            while i < len(word):
                if i < len(word) - 1 and word[i] == best[0] and word[i + 1] == best[1]:
                    merged.append(best[0] + best[1])
                    i += 2
                else:
                    merged.append(word[i])
                    i += 1
            word = merged
        out = " ".join(word)
        self._cache[token] = out
        return out

    def encode(self, text: str) -> list[int]:
        """Text -> BPE ids, without <|startoftext|>/<|endoftext|>."""
        ids = []
        for piece in self._pattern.findall(_clean(text, self._fix_text)):
            piece = "".join(self.byte_encoder[b] for b in piece.encode("utf-8"))
            ids.extend(self.encoder[t] for t in self.bpe(piece).split(" "))
        return ids

    def decode(self, ids) -> str:
        special = (self.sot_token, self.eot_token)
        text = "".join(self.decoder[int(i)] for i in ids if int(i) not in special)
        data = bytearray(self.byte_decoder[c] for c in text)
        return data.decode("utf-8", errors="replace").replace("</w>", " ").strip()

    def count_tokens(self, texts) -> list[int]:
        return [len(self.encode(t)) + 2 for t in texts]

    def __call__(self, texts) -> tuple[torch.Tensor, int]:
        """B texts -> ids (B, context_length) int64 [SOT, ..., EOT, 0, ...] and how many were cut
        (a cut sequence keeps its EOT as the last position)."""
        ids = torch.zeros(len(texts), self.context_length, dtype=torch.long)
        truncated = 0
        for row, text in enumerate(texts):
            seq = [self.sot_token] + self.encode(text) + [self.eot_token]
            if len(seq) > self.context_length:
                seq = seq[: self.context_length]
                seq[-1] = self.eot_token
                truncated += 1
            ids[row, : len(seq)] = torch.tensor(seq)
        return ids, truncated


# --------------------------------------------------------------------------------------------
# Model
# --------------------------------------------------------------------------------------------


@dataclass
class CLIPTextConfig:
    vocab_size: int = 49408
    context_length: int = 77
    width: int = 512
    heads: int = 8
    layers: int = 12
    embed_dim: int = 512  # text_projection output
    activation: str = "quick_gelu"  # OpenAI weights; "gelu" for LAION-trained open_clip weights


class LayerNorm(nn.LayerNorm):
    """Computed in float32 with float32 parameters, returned in the input dtype (OpenAI's)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return super().forward(x.float()).to(x.dtype)


class QuickGELU(nn.Module):
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * torch.sigmoid(1.702 * x)


class CausalSelfAttention(nn.Module):
    """Parameters named like nn.MultiheadAttention (in_proj_weight/bias, out_proj)."""

    def __init__(self, width: int, heads: int):
        super().__init__()
        self.heads = heads
        self.in_proj_weight = nn.Parameter(torch.empty(3 * width, width))
        self.in_proj_bias = nn.Parameter(torch.zeros(3 * width))
        self.out_proj = nn.Linear(width, width)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        B, L, W = x.shape
        q, k, v = F.linear(x, self.in_proj_weight, self.in_proj_bias).chunk(3, dim=-1)
        q, k, v = (t.view(B, L, self.heads, W // self.heads).transpose(1, 2) for t in (q, k, v))
        # The additive -inf mask in the input dtype, as nn.MultiheadAttention hands OpenAI's mask to
        # this call: the same attention kernel is chosen on a GPU (is_causal would pick another).
        mask = torch.full((L, L), float("-inf"), dtype=x.dtype, device=x.device).triu(1)
        y = F.scaled_dot_product_attention(q, k, v, attn_mask=mask)
        return self.out_proj(y.transpose(1, 2).reshape(B, L, W))


class MLP(nn.Module):
    def __init__(self, width: int, activation: str):
        super().__init__()
        self.c_fc = nn.Linear(width, 4 * width)
        self.act = QuickGELU() if activation == "quick_gelu" else nn.GELU()
        self.c_proj = nn.Linear(4 * width, width)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.c_proj(self.act(self.c_fc(x)))


class ResidualAttentionBlock(nn.Module):
    def __init__(self, width: int, heads: int, activation: str):
        super().__init__()
        self.ln_1 = LayerNorm(width)
        self.attn = CausalSelfAttention(width, heads)
        self.ln_2 = LayerNorm(width)
        self.mlp = MLP(width, activation)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = x + self.attn(self.ln_1(x))
        return x + self.mlp(self.ln_2(x))


class Transformer(nn.Module):
    def __init__(self, width: int, heads: int, layers: int, activation: str):
        super().__init__()
        self.resblocks = nn.ModuleList(
            ResidualAttentionBlock(width, heads, activation) for _ in range(layers)
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        for block in self.resblocks:
            x = block(x)
        return x


class CLIPTextTransformer(nn.Module):
    """ids (B, 77) -> (sentence (B, 512) projected EOT feature, words (B, 77, 512) after ln_final)."""

    def __init__(self, cfg: CLIPTextConfig = CLIPTextConfig(), init: bool = True):
        super().__init__()
        if cfg.activation not in ("quick_gelu", "gelu"):
            raise ValueError(
                f"activation must be 'quick_gelu' (OpenAI weights) or 'gelu' (LAION), not {cfg.activation!r}"
            )
        self.cfg = cfg
        self.token_embedding = nn.Embedding(cfg.vocab_size, cfg.width)
        self.positional_embedding = nn.Parameter(torch.empty(cfg.context_length, cfg.width))
        self.transformer = Transformer(cfg.width, cfg.heads, cfg.layers, cfg.activation)
        self.ln_final = LayerNorm(cfg.width)
        self.text_projection = nn.Parameter(torch.empty(cfg.width, cfg.embed_dim))
        if init:
            self.reset_parameters()

    def reset_parameters(self) -> None:
        """CLIP's initialization (used only for random-weight models in tests and smoke runs)."""
        w, n = self.cfg.width, self.cfg.layers
        nn.init.normal_(self.token_embedding.weight, std=0.02)
        nn.init.normal_(self.positional_embedding, std=0.01)
        proj_std, attn_std, fc_std = w**-0.5 * (2 * n) ** -0.5, w**-0.5, (2 * w) ** -0.5
        for block in self.transformer.resblocks:
            nn.init.normal_(block.attn.in_proj_weight, std=attn_std)
            nn.init.normal_(block.attn.out_proj.weight, std=proj_std)
            nn.init.normal_(block.mlp.c_fc.weight, std=fc_std)
            nn.init.normal_(block.mlp.c_proj.weight, std=proj_std)
        nn.init.normal_(self.text_projection, std=w**-0.5)

    def to_float16(self) -> "CLIPTextTransformer":
        """OpenAI's convert_weights: Linear and attention weights and biases and text_projection
        become float16 (the compute dtype); embeddings and LayerNorm parameters stay float32."""
        for module in self.modules():
            if isinstance(module, nn.Linear):
                module.half()
            elif isinstance(module, CausalSelfAttention):
                module.in_proj_weight.data = module.in_proj_weight.data.half()
                module.in_proj_bias.data = module.in_proj_bias.data.half()
        self.text_projection.data = self.text_projection.data.half()
        return self

    def forward(self, ids: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """In the dtype of text_projection: sentence (B, 512), words (B, L, 512)."""
        dtype = self.text_projection.dtype
        x = self.token_embedding(ids).to(dtype) + self.positional_embedding[: ids.shape[1]].to(dtype)
        words = self.ln_final(self.transformer(x))
        eot = ids.argmax(dim=-1)  # <|endoftext|> has the largest id
        sentence = words[torch.arange(ids.shape[0], device=ids.device), eot] @ self.text_projection
        return sentence, words


# --------------------------------------------------------------------------------------------
# Loading checkpoints
# --------------------------------------------------------------------------------------------

_IGNORED = ("logit_scale", "logit_bias", "input_resolution", "context_length", "vocab_size")


def _is_torchscript(path: Path) -> bool:
    if not zipfile.is_zipfile(path):
        return False
    with zipfile.ZipFile(path) as z:
        names = z.namelist()
    return any(n.endswith("/constants.pkl") or "/code/" in n for n in names)


def read_state_dict(path: str | Path) -> dict[str, torch.Tensor]:
    """All tensors of a checkpoint file (.safetensors, torch.save'd state dict, or TorchScript)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"CLIP weights file not found: {path}; expected {WEIGHTS_HINT}")
    if path.suffix == ".safetensors":
        try:
            from safetensors.torch import load_file  # optional dependency (the clip extra)
        except ImportError as e:
            raise ImportError(
                f"reading {path.name} needs the 'safetensors' package: pip install safetensors"
            ) from e
        return dict(load_file(str(path), device="cpu"))
    if _is_torchscript(path):
        return read_torchscript_tensors(path)  # never loaded as TorchScript: that runs its code
    try:
        obj = torch.load(str(path), map_location="cpu", weights_only=True)
    except (RuntimeError, pickle.UnpicklingError, EOFError, OSError) as e:
        raise ValueError(
            f"cannot read the CLIP weights {path} ({e}); the file is damaged or not a checkpoint: "
            f"{WEIGHTS_HINT}"
        ) from e
    if isinstance(obj, Mapping) and isinstance(obj.get("state_dict"), Mapping):
        obj = obj["state_dict"]  # an open_clip training checkpoint
    if not isinstance(obj, Mapping):
        raise ValueError(f"{path} holds a {type(obj).__name__}, not a state dict; expected {WEIGHTS_HINT}")
    return dict(obj)


def text_tower_state_dict(
    state: Mapping[str, torch.Tensor], source: str = "state dict"
) -> dict[str, torch.Tensor]:
    """The text-tower tensors of a full CLIP state dict, as float32; visual.* and scalars dropped."""
    out = {}
    for key, value in state.items():
        if key.startswith("module."):
            key = key[len("module.") :]
        if key.startswith("visual.") or key in _IGNORED or key.endswith("attn_mask"):
            continue
        if not torch.is_tensor(value):
            raise ValueError(f"{source}: entry {key!r} is a {type(value).__name__}, not a tensor")
        out[key] = value.detach().to(torch.float32)
    return out


def load_text_tower(model: CLIPTextTransformer, state: Mapping[str, torch.Tensor], source: str) -> None:
    state = text_tower_state_dict(state, source)
    expected = model.state_dict()
    missing = sorted(set(expected) - set(state))
    unexpected = sorted(set(state) - set(expected))
    if missing or unexpected:
        raise ValueError(
            f"{source} is not a CLIP ViT-B/32 text tower in open_clip/OpenAI key names: "
            f"missing {missing[:6]}{' ...' if len(missing) > 6 else ''}, "
            f"unexpected {unexpected[:6]}{' ...' if len(unexpected) > 6 else ''}; expected {WEIGHTS_HINT}"
        )
    wrong = [
        f"{k} {tuple(state[k].shape)} (expected {tuple(v.shape)})"
        for k, v in expected.items()
        if state[k].shape != v.shape
    ]
    if wrong:
        raise ValueError(
            f"{source}: shapes do not match CLIP ViT-B/32's text tower: {wrong[:4]}; expected {WEIGHTS_HINT}"
        )
    model.load_state_dict(state, strict=True)


def find_vocab() -> Path | None:
    """The vocabulary shipped inside an installed open_clip or OpenAI clip package (not imported)."""
    for package in ("open_clip", "clip"):
        try:
            spec = importlib.util.find_spec(package)
        except (ImportError, ValueError):
            continue
        if spec is not None and spec.origin:
            candidate = Path(spec.origin).parent / VOCAB_FILENAME
            if candidate.is_file():
                return candidate
    return None


# --------------------------------------------------------------------------------------------
# Encoder
# --------------------------------------------------------------------------------------------


class CLIPTextEncoder(TextEncoder):
    """CLIP ViT-B/32 text tower: sentence (B, 512), words (B, 77, 512) and word_mask (B, 77),
    all float32 whatever the precision; the mask ends at EOT (words="eot") or is all True ("all")."""

    name = "clip-vit-b32"

    def __init__(
        self,
        weights: str | Path | Mapping[str, torch.Tensor] | None = None,
        vocab: str | Path | None = None,
        activation: str = "quick_gelu",
        device: str | torch.device = "cpu",
        *,
        precision: str = "float16",
        words: str = "eot",
        random_init_seed: int | None = None,
    ):
        """weights: a checkpoint path or a state dict; None only with `random_init_seed`
        (random weights, for tests). vocab: bpe_simple_vocab_16e6.txt.gz (None: look inside an
        installed open_clip/clip package). precision: "float16" (OpenAI's, as MMM was trained) or
        "float32". words: "eot" (positions up to end-of-text) or "all" (all 77, as MMM attends)."""
        super().__init__()
        if precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {PRECISIONS}, not {precision!r}")
        if words not in WORD_MODES:
            raise ValueError(f"words must be one of {WORD_MODES}, not {words!r}")
        if weights is None and random_init_seed is None:
            raise ValueError(
                f"the 'clip' text encoder needs its weights file: pass weights=PATH to {WEIGHTS_HINT}"
            )
        if vocab is None:
            vocab = find_vocab()
            if vocab is None:
                raise ValueError(
                    f"the 'clip' text encoder needs its vocabulary file: pass vocab=PATH to {VOCAB_HINT}"
                )
        self.tokenizer = CLIPTokenizer(vocab)
        cfg = CLIPTextConfig(activation=activation)
        if self.tokenizer.vocab_size > cfg.vocab_size:
            raise ValueError(
                f"{vocab} defines {self.tokenizer.vocab_size} tokens, more than CLIP's {cfg.vocab_size}"
            )
        if weights is None:
            with torch.random.fork_rng(devices=[]):
                torch.manual_seed(random_init_seed)
                self.model = CLIPTextTransformer(cfg)
            self.weights_source = f"random(seed={random_init_seed})"
        else:
            # (Not on the meta device: its normal_ imports torch._dynamo, seconds on a small CPU.)
            self.model = CLIPTextTransformer(cfg, init=False)
            if isinstance(weights, Mapping):
                state, source = weights, "the given state dict"
            else:
                state, source = read_state_dict(weights), str(weights)
            load_text_tower(self.model, state, source)
            self.weights_source = source
        if precision == "float16":
            self.model.to_float16()
        self.activation, self.precision, self.words = activation, precision, words
        self.sentence_dim = cfg.embed_dim
        self.word_dim = cfg.width
        self.max_words = cfg.context_length
        self._freeze()
        self.to(device)

    def _weights_digest(self) -> str:
        extra = (
            f"activation={self.activation},vocab={self.tokenizer.vocab_sha256},precision={self.precision},"
            f"words={self.words},cleanup={self.tokenizer.cleanup}"
        )
        return state_dict_digest(self.model.state_dict(), extra=extra)

    def count_tokens(self, texts) -> list[int]:
        return self.tokenizer.count_tokens(texts)

    def _encode(self, texts: list[str]) -> TextEmbedding:
        ids, truncated = self.tokenizer(texts)
        ids = ids.to(self.device)
        sentence, words = self.model(ids)
        words = words.float()
        if self.words == "all":
            mask = torch.ones(ids.shape, dtype=torch.bool, device=ids.device)
        else:
            eot = ids.argmax(dim=-1, keepdim=True)
            mask = torch.arange(ids.shape[1], device=ids.device).unsqueeze(0) <= eot
            words = words * mask.unsqueeze(-1)  # zeroed where masked, as in cached embeddings
        return TextEmbedding(sentence.float(), words, mask, truncated)
