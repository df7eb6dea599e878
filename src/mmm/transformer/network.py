"""The conditional masked transformer of MMM (stage 2).

Token sequence (B, M): codes in [0, K), then END = K, then PAD = K + 1; MASK = K + 2 marks what
the model must fill in. Text: a sentence embedding (B, Ds) and word embeddings (B, Lw, Dw) with
a mask of real words. Output: logits over the K codes at every motion position (B, M, K).

    tokens --(codebook vectors | learned specials)--> C --linear--> E  + sinusoidal positions
      -> num_cross_layers "local" layers: cross-attention to the projected words (padding masked)
      -> [projected sentence, tokens] -> self-attention layers (keys after END masked)
      -> final LayerNorm -> linear E -> K

Part-aware variant (upper-body editing): with a `condition_codebook` (the lower-body codebook of a
part-aware tokenizer), a second token sequence (B, M) of lower-body codes, same id layout with
their own END/PAD/MASK, is embedded the same way and added position by position. The model then
predicts upper-body codes given the lower body and the text; MASK in the condition hides those
lower-body codes (training masks a random share, editing chooses how much to keep).

Two things the released code gets wrong are fixed here: padded word positions are masked in
cross-attention, and the positional encoding is added once, not twice. Attention is PyTorch's
scaled_dot_product_attention with boolean masks; no row is ever fully masked (the text token and
at least one word are always visible), so nothing produces NaN. Dropped text (for classifier-free
guidance) is a learned null sentence and a single learned null word.

`variant="released"` computes what the authors' released weights compute (imported with
`mmm import released`), differing from the default in exactly these places:
    positions   the table is added to the motion tokens before the cross layers (only when there
                are any) and again to [sentence, tokens] after the sentence is prepended, so the
                motion token at index i carries table[i] + table[i + 1] and the sentence table[0];
    words       cross-attention reads every word position given, the word mask is ignored (the
                release feeds all 77 CLIP positions, those after the end-of-text token included);
    head        no bias;
    no text     there is no learned null text (the release trains without text dropout): dropped
                text is zero sentence and word features, with the sentence token hidden from
                attention as the release's `att_txt=False` does.
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

VARIANTS = ("fixed", "released")


@dataclass
class TransformerConfig:
    embed_dim: int = 1024  # E
    num_heads: int = 16
    num_layers: int = 18  # all layers, the cross-attention ones included
    num_cross_layers: int = 1
    mlp_ratio: int = 4
    dropout: float = 0.1
    max_tokens: int = 50  # M: 196 frames / 4 + END
    variant: str = (
        "fixed"  # fixed (this package's) | released (the authors' forward pass, for imported weights)
    )

    def __post_init__(self):
        if self.variant not in VARIANTS:
            raise ValueError(
                f"model.transformer.variant must be one of {', '.join(VARIANTS)}, got {self.variant!r}"
            )
        if not 0 <= self.num_cross_layers <= self.num_layers:
            raise ValueError(
                f"num_cross_layers={self.num_cross_layers} must be between 0 and num_layers={self.num_layers}"
            )
        if self.embed_dim % self.num_heads:
            raise ValueError(f"embed_dim={self.embed_dim} is not divisible by num_heads={self.num_heads}")


def sinusoidal_positions(length: int, dim: int) -> torch.Tensor:
    """(length, dim) sine/cosine position codes."""
    position = torch.arange(length, dtype=torch.float32).unsqueeze(1)
    freq = torch.exp(torch.arange(0, dim, 2, dtype=torch.float32) * (-math.log(10000.0) / dim))
    pe = torch.zeros(length, dim)
    pe[:, 0::2] = torch.sin(position * freq)
    pe[:, 1::2] = torch.cos(position * freq[: dim // 2])
    return pe


class Attention(nn.Module):
    """Multi-head attention of queries (B, S, E) over keys/values (B, T, E); key_mask (B, T) True =
    visible."""

    def __init__(self, dim: int, heads: int, dropout: float):
        super().__init__()
        self.heads, self.dropout = heads, dropout
        self.q = nn.Linear(dim, dim)
        self.kv = nn.Linear(dim, 2 * dim)
        self.out = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor, context: torch.Tensor, key_mask: torch.Tensor) -> torch.Tensor:
        return self.attend(x, self.keys_values(context), key_mask)

    def keys_values(self, context: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Keys and values (B, heads, T, E / heads) of the context (B, T, E); inference caches them."""
        B, T, _ = context.shape
        k, v = self.kv(context).view(B, T, 2, self.heads, -1).permute(2, 0, 3, 1, 4)
        return k, v

    def attend(
        self, x: torch.Tensor, kv: tuple[torch.Tensor, torch.Tensor], key_mask: torch.Tensor
    ) -> torch.Tensor:
        B, S, E = x.shape
        q = self.q(x).view(B, S, self.heads, -1).transpose(1, 2)
        k, v = kv
        mask, dropout_p = key_mask[:, None, None, :], self.dropout if self.training else 0.0
        if q.device.type == "cpu" and q.dtype == torch.bfloat16:
            # PyTorch's CPU attention kernel is several times slower in bfloat16 than in float32 on
            # these short sequences (the backward 3-8x on an AVX-512 CPU without AMX; README "Training
            # speed"), and it is a small share of the step's arithmetic, so it runs in float32.
            with torch.autocast("cpu", enabled=False):
                y = F.scaled_dot_product_attention(
                    q.float(), k.float(), v.float(), attn_mask=mask, dropout_p=dropout_p
                ).to(q.dtype)
        else:
            y = F.scaled_dot_product_attention(q, k, v, attn_mask=mask, dropout_p=dropout_p)
        return self.out(y.transpose(1, 2).reshape(B, S, E))


class MLP(nn.Sequential):
    def __init__(self, dim: int, ratio: int, dropout: float):
        super().__init__(
            nn.Linear(dim, ratio * dim), nn.GELU(), nn.Linear(ratio * dim, dim), nn.Dropout(dropout)
        )


class SelfAttentionBlock(nn.Module):
    """Pre-LN: x + attn(ln(x)) over the visible keys; x + mlp(ln(x))."""

    def __init__(self, cfg: TransformerConfig):
        super().__init__()
        E = cfg.embed_dim
        self.ln1, self.ln2 = nn.LayerNorm(E), nn.LayerNorm(E)
        self.attn = Attention(E, cfg.num_heads, cfg.dropout)
        self.mlp = MLP(E, cfg.mlp_ratio, cfg.dropout)
        self.drop = nn.Dropout(cfg.dropout)

    def forward(self, x: torch.Tensor, key_mask: torch.Tensor) -> torch.Tensor:
        h = self.ln1(x)
        x = x + self.drop(self.attn(h, h, key_mask))
        return x + self.mlp(self.ln2(x))


class CrossAttentionBlock(nn.Module):
    """Pre-LN "local" layer: motion tokens attend to the words, then an MLP."""

    def __init__(self, cfg: TransformerConfig):
        super().__init__()
        E = cfg.embed_dim
        self.ln_x, self.ln_words, self.ln2 = nn.LayerNorm(E), nn.LayerNorm(E), nn.LayerNorm(E)
        self.attn = Attention(E, cfg.num_heads, cfg.dropout)
        self.mlp = MLP(E, cfg.mlp_ratio, cfg.dropout)
        self.drop = nn.Dropout(cfg.dropout)

    def forward(self, x: torch.Tensor, words: torch.Tensor, word_mask: torch.Tensor | None) -> torch.Tensor:
        """word_mask (B, Lw) True = visible; None: every word position is read."""
        mask = (
            word_mask
            if word_mask is not None
            else torch.ones(words.shape[:2], dtype=torch.bool, device=words.device)
        )
        x = x + self.drop(self.attn(self.ln_x(x), self.ln_words(words), mask))
        return x + self.mlp(self.ln2(x))

    def word_keys_values(self, words: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The keys and values `forward` computes from the words: the same for every decoding pass."""
        return self.attn.keys_values(self.ln_words(words))

    def forward_cached(
        self, x: torch.Tensor, kv: tuple[torch.Tensor, torch.Tensor], word_mask: torch.Tensor
    ) -> torch.Tensor:
        """`forward` with the words' keys and values from `word_keys_values` (inference only)."""
        x = x + self.attn.attend(self.ln_x(x), kv, word_mask)
        return x + self.mlp(self.ln2(x))


@dataclass
class TextContext:
    """What every decoding pass of a batch reads from its text, computed once per sample
    (`MaskedMotionTransformer.text_context`): the projected sentence token, each cross layer's
    keys and values of the words, the visible words and whether the sentence token is visible."""

    sentence: torch.Tensor  # (B, E)
    word_kv: list[tuple[torch.Tensor, torch.Tensor]]  # per cross layer: (B, heads, Lw, E / heads) each
    word_mask: torch.Tensor  # (B, Lw) bool
    see_text: torch.Tensor  # (B,) bool

    def select(self, index: torch.Tensor | None) -> "TextContext":
        """The rows `index` (None: all)."""
        if index is None:
            return self
        return TextContext(
            self.sentence[index],
            [(k[index], v[index]) for k, v in self.word_kv],
            self.word_mask[index],
            self.see_text[index],
        )


def embed_ids(
    tokens: torch.Tensor, codebook: torch.Tensor, special: nn.Embedding, proj: nn.Linear
) -> torch.Tensor:
    """(B, M) ids -> (B, M, E): codebook (K, C) vectors for codes [0, K), the learned `special`
    vectors for END = K, PAD = K + 1 and MASK = K + 2, then `proj` to E."""
    K = codebook.shape[0]
    codes = F.embedding(tokens.clamp(max=K - 1), codebook)
    specials = special((tokens - K).clamp(min=0))
    return proj(torch.where((tokens < K).unsqueeze(-1), codes, specials))


class TokenEmbedding(nn.Module):
    """The conditioning part's embedding: its own frozen codebook (K, C), specials and projection."""

    def __init__(self, codebook: torch.Tensor, dim: int):
        super().__init__()
        self.num_codes = codebook.shape[0]
        self.end_id, self.pad_id, self.mask_id = self.num_codes, self.num_codes + 1, self.num_codes + 2
        self.register_buffer("codebook", codebook.detach().clone().float())
        self.special = nn.Embedding(3, codebook.shape[1])
        self.proj = nn.Linear(codebook.shape[1], dim)

    def forward(self, tokens: torch.Tensor) -> torch.Tensor:
        return embed_ids(tokens, self.codebook, self.special, self.proj)


class MaskedMotionTransformer(nn.Module):
    """Predicts motion codes at every position from a partly masked token sequence and text.

    codebook: (K, C) stage-1 code vectors, kept frozen as a buffer. condition_codebook: (Kc, Cc)
    code vectors of the conditioning part (the lower body), or None for the plain model.
    """

    def __init__(
        self,
        codebook: torch.Tensor,
        cfg: TransformerConfig,
        sentence_dim: int,
        word_dim: int,
        condition_codebook: torch.Tensor | None = None,
    ):
        super().__init__()
        self.cfg = cfg
        K, C = codebook.shape
        E = cfg.embed_dim
        self.num_codes = K
        self.end_id, self.pad_id, self.mask_id = K, K + 1, K + 2
        self.released = cfg.variant == "released"
        if self.released and condition_codebook is not None:
            raise ValueError(
                "the released variant has no part-aware form: train the part-aware model with variant=fixed"
            )
        self.register_buffer("codebook", codebook.detach().clone().float())
        self.special = nn.Embedding(3, C)
        self.token_proj = nn.Linear(C, E)
        self.condition = None if condition_codebook is None else TokenEmbedding(condition_codebook, E)
        # The released form also positions the prepended sentence: one more row.
        self.register_buffer(
            "positions", sinusoidal_positions(cfg.max_tokens + self.released, E), persistent=False
        )
        self.sentence_proj = nn.Linear(sentence_dim, E)
        self.word_proj = nn.Linear(word_dim, E)
        if not self.released:
            self.null_sentence = nn.Parameter(torch.zeros(E))
            self.null_word = nn.Parameter(torch.zeros(E))
        self.cross_layers = nn.ModuleList(CrossAttentionBlock(cfg) for _ in range(cfg.num_cross_layers))
        self.layers = nn.ModuleList(
            SelfAttentionBlock(cfg) for _ in range(cfg.num_layers - cfg.num_cross_layers)
        )
        self.ln_f = nn.LayerNorm(E)
        self.head = nn.Linear(E, K, bias=not self.released)
        self.apply(self._init)

    @staticmethod
    def _init(module: nn.Module) -> None:
        if isinstance(module, nn.Linear):
            nn.init.normal_(module.weight, std=0.02)
            if module.bias is not None:
                nn.init.zeros_(module.bias)
        elif isinstance(module, nn.Embedding):
            nn.init.normal_(module.weight, std=0.02)
        elif isinstance(module, nn.LayerNorm):
            nn.init.ones_(module.weight)
            nn.init.zeros_(module.bias)

    @property
    def part_aware(self) -> bool:
        return self.condition is not None

    def embed_tokens(self, tokens: torch.Tensor) -> torch.Tensor:
        """(B, M) ids -> (B, M, E): codebook vectors for codes, learned vectors for END/PAD/MASK."""
        return embed_ids(tokens, self.codebook, self.special, self.token_proj)

    def project_text(
        self, sentence: torch.Tensor, words: torch.Tensor, word_mask: torch.Tensor, drop: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(sentence token (B, D), word features (B, Lw, D), word mask (B, Lw)), the rows where
        drop (B,) is True replaced by the learned null text (one null word, the rest masked)."""
        s = self.sentence_proj(sentence)
        w = self.word_proj(words)
        # Always through torch.where, so the null text takes part in every graph (DDP expects
        # every parameter to receive a gradient, a zero one included).
        s = torch.where(drop[:, None], self.null_sentence.expand_as(s), s)
        null_words = torch.zeros_like(w[:, :1]) + self.null_word
        w = torch.where(drop[:, None, None], torch.cat((null_words, w[:, 1:]), dim=1), w)
        first_only = torch.zeros_like(word_mask)
        first_only[:, 0] = True
        return s, w, torch.where(drop[:, None], first_only, word_mask)

    def forward(
        self,
        tokens: torch.Tensor,
        sentence: torch.Tensor,
        words: torch.Tensor,
        word_mask: torch.Tensor,
        drop_text: torch.Tensor | None = None,
        condition: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Logits (B, M, K).

        tokens (B, M) with END after the last code and PAD after END; sentence (B, Ds);
        words (B, Lw, Dw); word_mask (B, Lw) True at real words; drop_text (B,) True replaces the
        text by the learned null text (the unconditional branch of classifier-free guidance);
        condition (B, M): the part-aware model's lower-body codes (MASK where hidden).
        """
        B, M = tokens.shape
        if (condition is None) != (self.condition is None):
            raise ValueError(
                "a part-aware transformer needs the lower-body condition tokens; a plain one takes none"
                if condition is None
                else "condition tokens given to a transformer that is not part-aware"
            )
        if self.released:
            return self._forward_released(tokens, sentence, words, drop_text)
        x = self.embed_tokens(tokens) + self.positions[:M]
        if condition is not None:
            if condition.shape != tokens.shape:
                raise ValueError(
                    f"condition tokens {tuple(condition.shape)} must have the shape of the tokens "
                    f"{tuple(tokens.shape)}"
                )
            x = x + self.condition(condition)
        drop = drop_text if drop_text is not None else torch.zeros(B, dtype=torch.bool, device=tokens.device)
        s, w, word_mask = self.project_text(sentence, words, word_mask, drop)
        for layer in self.cross_layers:
            x = layer(x, w, word_mask)
        x = torch.cat((s.unsqueeze(1), x), dim=1)
        # Visible keys: the text token and every position up to and including END.
        key_mask = torch.cat((torch.ones_like(tokens[:, :1], dtype=torch.bool), tokens != self.pad_id), dim=1)
        for layer in self.layers:
            x = layer(x, key_mask)
        return self.head(self.ln_f(x[:, 1:]))

    # -- inference (decoding): the same arithmetic as `forward`, less work per pass -------------
    def _autocast(self, device: torch.device):
        """bfloat16 autocast when this is an inference copy made for it (mmm.generation.precision)."""
        dtype = getattr(self, "inference_autocast", None)
        if dtype is None:
            return contextlib.nullcontext()
        return torch.autocast(device.type, dtype=dtype)

    def text_context(
        self,
        sentence: torch.Tensor,
        words: torch.Tensor,
        word_mask: torch.Tensor,
        drop_text: torch.Tensor | None = None,
    ) -> TextContext:
        """What `forward` computes from the text alone, once for all the passes of a decoding."""
        with self._autocast(sentence.device):
            B = sentence.shape[0]
            drop = (
                drop_text
                if drop_text is not None
                else torch.zeros(B, dtype=torch.bool, device=sentence.device)
            )
            if self.released:
                see_text = ~drop
                if drop_text is not None:
                    sentence = sentence * see_text[:, None].to(sentence.dtype)
                    words = words * see_text[:, None, None].to(words.dtype)
                mask = torch.ones(words.shape[:2], dtype=torch.bool, device=words.device)
                s = self.sentence_proj(sentence)
                w = self.word_proj(words) if self.cross_layers else None
            else:
                see_text = torch.ones_like(drop)
                s, w, mask = self.project_text(sentence, words, word_mask, drop)
            kv = [layer.word_keys_values(w) for layer in self.cross_layers]
        return TextContext(s, kv, mask, see_text)

    def forward_cached(
        self,
        tokens: torch.Tensor,
        context: TextContext,
        condition: torch.Tensor | None = None,
        head_rows: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Logits of `forward` from a `text_context` (B rows, like tokens): (B, M, K), or (N, K) at
        the N positions `head_rows` (N,) names (flat indices into B * M) when given, the output
        head evaluated there only. Float32 logits whatever the precision."""
        B, M = tokens.shape
        with self._autocast(tokens.device):
            x = self.embed_tokens(tokens)
            if self.released:
                if self.cross_layers:
                    x = x + self.positions[:M]
                    for layer, kv in zip(self.cross_layers, context.word_kv):
                        x = layer.forward_cached(x, kv, context.word_mask)
                x = torch.cat((context.sentence.unsqueeze(1).to(x.dtype), x), dim=1) + self.positions[: M + 1]
                key_mask = torch.cat((context.see_text[:, None], tokens != self.pad_id), dim=1)
            else:
                x = x + self.positions[:M]
                if condition is not None:
                    x = x + self.condition(condition)
                for layer, kv in zip(self.cross_layers, context.word_kv):
                    x = layer.forward_cached(x, kv, context.word_mask)
                x = torch.cat((context.sentence.unsqueeze(1).to(x.dtype), x), dim=1)
                key_mask = torch.cat(
                    (torch.ones_like(tokens[:, :1], dtype=torch.bool), tokens != self.pad_id), dim=1
                )
            for layer in self.layers:
                x = layer(x, key_mask)
            x = x[:, 1:]
            if head_rows is not None:
                x = x.reshape(B * M, -1).index_select(0, head_rows)
            return self.head(self.ln_f(x)).float()

    def _forward_released(
        self,
        tokens: torch.Tensor,
        sentence: torch.Tensor,
        words: torch.Tensor,
        drop_text: torch.Tensor | None,
    ) -> torch.Tensor:
        """The released forward pass (see the module docstring); logits (B, M, K)."""
        B, M = tokens.shape
        see_text = torch.ones(B, dtype=torch.bool, device=tokens.device)
        if drop_text is not None:
            see_text = ~drop_text
            sentence = sentence * see_text[:, None].to(sentence.dtype)
            words = words * see_text[:, None, None].to(words.dtype)
        x = self.embed_tokens(tokens)
        if self.cross_layers:
            x = x + self.positions[:M]
            w = self.word_proj(words)
            for layer in self.cross_layers:
                x = layer(x, w, None)
        x = torch.cat((self.sentence_proj(sentence).unsqueeze(1), x), dim=1) + self.positions[: M + 1]
        key_mask = torch.cat((see_text[:, None], tokens != self.pad_id), dim=1)
        for layer in self.layers:
            x = layer(x, key_mask)
        return self.head(self.ln_f(x[:, 1:]))
