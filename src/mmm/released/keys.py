"""Key maps between the authors' released checkpoints and this package's state dicts, both ways.

Released stage 1 (`{"net": ...}`, 67 entries at the paper size) and stage 2 (`{"trans": ...}`,
306 entries plus the whole stage-1 model again under `trans_base.vqvae.`); names and shapes as in
../shared/spec/released-checkpoints.md. Sizes are read off the shapes; the table of every key and
its shape is then rebuilt from those sizes and compared with the file, so a missing, extra or
mis-shaped key is an error that names it. Tensors that the released forward pass never uses
(`pos_embedding`, the cross-attention `attn.mask`) and the fixed sinusoidal table are checked and
left out; everything else has exactly one place here.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import torch

from mmm.tokenizer.network import TokenizerConfig
from mmm.transformer.network import TransformerConfig, sinusoidal_positions

VQ_PREFIX = "trans_base.vqvae."  # the stage-1 model inside a stage-2 checkpoint
CLIP_POSITIONS = 77  # the released cross-attention's unused mask is (1, 1, block, 77)


class ReleasedKeyError(ValueError):
    """A released checkpoint whose keys or shapes are not the documented ones."""


def _check(given: Mapping[str, torch.Tensor], expected: dict[str, tuple], source: str, what: str) -> None:
    missing = sorted(set(expected) - set(given))
    extra = sorted(set(given) - set(expected))
    wrong = [
        f"{k} {tuple(given[k].shape)} (expected {expected[k]})"
        for k in sorted(set(given) & set(expected))
        if tuple(given[k].shape) != expected[k]
    ]
    problems = []
    if missing:
        problems.append(f"missing {', '.join(missing[:8])}{' ...' if len(missing) > 8 else ''}")
    if extra:
        problems.append(f"unmapped {', '.join(extra[:8])}{' ...' if len(extra) > 8 else ''}")
    if wrong:
        problems.append(f"wrongly shaped {', '.join(wrong[:6])}{' ...' if len(wrong) > 6 else ''}")
    if problems:
        raise ReleasedKeyError(f"{source}: not a released {what} checkpoint: {'; '.join(problems)}")


def _need(state: Mapping[str, torch.Tensor], key: str, source: str, what: str) -> torch.Tensor:
    if key not in state:
        raise ReleasedKeyError(f"{source}: not a released {what} checkpoint: missing {key}")
    return state[key]


def _count(state: Mapping[str, torch.Tensor], pattern: str) -> int:
    """How many i make `pattern.format(i)` a key (consecutive from 0)."""
    n = 0
    while pattern.format(n) in state:
        n += 1
    return n


# -- stage 1 ----------------------------------------------------------------------------------------
@dataclass
class ReleasedVQSizes:
    feature_dim: int
    width: int
    code_dim: int
    num_codes: int
    down_t: int
    depth: int

    def config(self, dilation_growth: int = 3) -> TokenizerConfig:
        return TokenizerConfig(
            width=self.width,
            num_codes=self.num_codes,
            code_dim=self.code_dim,
            down_t=self.down_t,
            depth=self.depth,
            dilation_growth=dilation_growth,
        )


def vq_sizes(net: Mapping[str, torch.Tensor], source: str) -> ReleasedVQSizes:
    first = _need(net, "vqvae.encoder.model.0.weight", source, "stage-1 (VQ-VAE)")
    codebook = _need(net, "vqvae.quantizer.codebook", source, "stage-1 (VQ-VAE)")
    down_t = 0  # the down-sampling blocks are model.2, model.3, ... (0 and 1: the first conv and its ReLU)
    while f"vqvae.encoder.model.{2 + down_t}.0.weight" in net:
        down_t += 1
    depth = _count(net, "vqvae.encoder.model.2.1.model.{}.conv1.weight")
    if down_t < 1 or depth < 1:
        raise ReleasedKeyError(
            f"{source}: not a released stage-1 (VQ-VAE) checkpoint: no down-sampling blocks "
            "vqvae.encoder.model.2.*"
        )
    return ReleasedVQSizes(
        int(first.shape[1]),
        int(first.shape[0]),
        int(codebook.shape[1]),
        int(codebook.shape[0]),
        down_t,
        depth,
    )


def _vq_names(s: ReleasedVQSizes) -> dict[str, str]:
    """Released stage-1 tensor name -> this package's TokenizerModule name (weights and biases)."""
    names: dict[str, str] = {}

    def conv(released: str, ours: str) -> None:
        for p in ("weight", "bias"):
            names[f"vqvae.{released}.{p}"] = f"tokenizer.{ours}.{p}"

    def stack(released: str, ours: str) -> None:
        for j in range(s.depth):
            conv(f"{released}.model.{j}.conv1", f"{ours}.{j}.conv")
            conv(f"{released}.model.{j}.conv2", f"{ours}.{j}.proj")

    # Encoder: released model.{0, 2..1+down_t (Sequential(down conv, R)), 2+down_t}; ours one flat Sequential.
    conv("encoder.model.0", "encoder.net.0")
    for i in range(s.down_t):
        conv(f"encoder.model.{2 + i}.0", f"encoder.net.{2 + 2 * i}")
        stack(f"encoder.model.{2 + i}.1", f"encoder.net.{3 + 2 * i}")
    conv(f"encoder.model.{2 + s.down_t}", f"encoder.net.{2 + 2 * s.down_t}")
    # Decoder: released model.{0, 2..1+down_t (Sequential(R, upsample, conv)), 2+down_t, 4+down_t}.
    conv("decoder.model.0", "decoder.net.0")
    for i in range(s.down_t):
        stack(f"decoder.model.{2 + i}.0", f"decoder.net.{2 + 3 * i}")
        conv(f"decoder.model.{2 + i}.2", f"decoder.net.{4 + 3 * i}")
    conv(f"decoder.model.{2 + s.down_t}", f"decoder.net.{2 + 3 * s.down_t}")
    conv(f"decoder.model.{4 + s.down_t}", f"decoder.net.{4 + 3 * s.down_t}")
    names["vqvae.quantizer.codebook"] = "tokenizer.quantizer.codebook"
    return names


def _vq_shapes(s: ReleasedVQSizes) -> dict[str, tuple]:
    W, C, D = s.width, s.code_dim, s.feature_dim
    shapes: dict[str, tuple] = {}

    def conv(name: str, out: int, inp: int, k: int) -> None:
        shapes[f"vqvae.{name}.weight"], shapes[f"vqvae.{name}.bias"] = (out, inp, k), (out,)

    def stack(name: str) -> None:
        for j in range(s.depth):
            conv(f"{name}.model.{j}.conv1", W, W, 3)
            conv(f"{name}.model.{j}.conv2", W, W, 1)

    conv("encoder.model.0", W, D, 3)
    for i in range(s.down_t):
        conv(f"encoder.model.{2 + i}.0", W, W, 4)
        stack(f"encoder.model.{2 + i}.1")
    conv(f"encoder.model.{2 + s.down_t}", C, W, 3)
    conv("decoder.model.0", W, C, 3)
    for i in range(s.down_t):
        stack(f"decoder.model.{2 + i}.0")
        conv(f"decoder.model.{2 + i}.2", W, W, 3)
    conv(f"decoder.model.{2 + s.down_t}", W, W, 3)
    conv(f"decoder.model.{4 + s.down_t}", D, W, 3)
    shapes["vqvae.quantizer.codebook"] = (s.num_codes, C)
    return shapes


def tokenizer_from_released(
    net: Mapping[str, torch.Tensor], source: str
) -> tuple[dict[str, torch.Tensor], ReleasedVQSizes]:
    """TokenizerModule tensors (without mean/std) of a released stage-1 state dict, and its sizes.

    The EMA statistics are not in the release: they restart from the codebook (count 1 per code),
    which is what a fine-tuning run would need; usage is empty."""
    sizes = vq_sizes(net, source)
    _check(net, _vq_shapes(sizes), source, "stage-1 (VQ-VAE)")
    state = {ours: net[released].detach().float().clone() for released, ours in _vq_names(sizes).items()}
    codebook = state["tokenizer.quantizer.codebook"]
    state["tokenizer.quantizer.ema_sum"] = codebook.clone()
    state["tokenizer.quantizer.ema_count"] = torch.ones(sizes.num_codes)
    state["tokenizer.quantizer.window_usage"] = torch.zeros(sizes.num_codes)
    state["tokenizer.quantizer.initialized"] = torch.tensor(True)
    return state, sizes


def tokenizer_to_released(
    state: Mapping[str, torch.Tensor], cfg: TokenizerConfig, feature_dim: int
) -> dict[str, torch.Tensor]:
    """The released stage-1 state dict (`net`) of a TokenizerModule state dict."""
    sizes = ReleasedVQSizes(feature_dim, cfg.width, cfg.code_dim, cfg.num_codes, cfg.down_t, cfg.depth)
    return {released: state[ours].detach().clone() for released, ours in _vq_names(sizes).items()}


# -- stage 2 ----------------------------------------------------------------------------------------
@dataclass
class ReleasedTransformerSizes:
    embed_dim: int
    code_dim: int
    num_codes: int
    sentence_dim: int
    word_dim: int
    cross_layers: int
    base_layers: int
    head_layers: int
    mlp_dim: int
    block_size: int

    def config(self, num_heads: int, dropout: float = 0.1) -> TransformerConfig:
        if self.mlp_dim % self.embed_dim:
            raise ReleasedKeyError(
                f"MLP width {self.mlp_dim} is not a multiple of the embedding {self.embed_dim}"
            )
        return TransformerConfig(
            embed_dim=self.embed_dim,
            num_heads=num_heads,
            num_layers=self.cross_layers + self.base_layers + self.head_layers,
            num_cross_layers=self.cross_layers,
            mlp_ratio=self.mlp_dim // self.embed_dim,
            dropout=dropout,
            max_tokens=self.block_size - 1,
            variant="released",
        )


def transformer_sizes(trans: Mapping[str, torch.Tensor], source: str) -> ReleasedTransformerSizes:
    what = "stage-2 (transformer)"
    to_emb = _need(trans, "trans_base.to_emb.weight", source, what)
    head = _need(trans, "trans_head.head.weight", source, what)
    cond = _need(trans, "trans_base.cond_emb.weight", source, what)
    table = _need(trans, "trans_base.pos_embed.embed", source, what)
    cross = _count(trans, "trans_base.cross_att.{}.ln1.weight")
    word = trans.get("trans_base.word_emb.weight")
    block = trans.get("trans_base.blocks.0.mlp.0.weight", trans.get("trans_head.blocks.0.mlp.0.weight"))
    if block is None:
        raise ReleasedKeyError(
            f"{source}: not a released {what} checkpoint: missing trans_base.blocks.0.mlp.0.weight"
        )
    return ReleasedTransformerSizes(
        embed_dim=int(to_emb.shape[0]),
        code_dim=int(to_emb.shape[1]),
        num_codes=int(head.shape[0]),
        sentence_dim=int(cond.shape[1]),
        word_dim=int(word.shape[1]) if word is not None else int(cond.shape[1]),
        cross_layers=cross,
        base_layers=_count(trans, "trans_base.blocks.{}.ln1.weight"),
        head_layers=_count(trans, "trans_head.blocks.{}.ln1.weight"),
        mlp_dim=int(block.shape[0]),
        block_size=int(table.shape[0]),
    )


def _block_names(released: str, ours: str, cross: bool) -> dict[str, str]:
    """Released block -> ours, for everything but the fused key/value projection."""
    names = {}
    norms = {"ln1": "ln_x", "ln2": "ln2", "ln3": "ln_words"} if cross else {"ln1": "ln1", "ln2": "ln2"}
    for theirs, mine in {
        **norms,
        "attn.query": "attn.q",
        "attn.proj": "attn.out",
        "mlp.0": "mlp.0",
        "mlp.2": "mlp.2",
    }.items():
        for p in ("weight", "bias"):
            names[f"{released}.{theirs}.{p}"] = f"{ours}.{mine}.{p}"
    return names


def _transformer_layout(
    s: ReleasedTransformerSizes,
) -> tuple[dict[str, str], list[tuple[str, str]], dict[str, tuple]]:
    """(released -> ours one to one, [(released block, our block)] whose key and value are fused
    into our `attn.kv`, every released key's shape)."""
    E, H = s.embed_dim, s.mlp_dim
    names = {
        "trans_base.learn_tok_emb.weight": "transformer.special.weight",
        "trans_head.head.weight": "transformer.head.weight",
    }
    for theirs, mine in {
        "trans_base.to_emb": "token_proj",
        "trans_base.cond_emb": "sentence_proj",
        "trans_head.ln_f": "ln_f",
    }.items():
        for p in ("weight", "bias"):
            names[f"{theirs}.{p}"] = f"transformer.{mine}.{p}"
    shapes = {
        "trans_base.learn_tok_emb.weight": (3, s.code_dim),
        "trans_base.to_emb.weight": (E, s.code_dim),
        "trans_base.to_emb.bias": (E,),
        "trans_base.cond_emb.weight": (E, s.sentence_dim),
        "trans_base.cond_emb.bias": (E,),
        "trans_base.pos_embedding.weight": (s.block_size, E),
        "trans_base.pos_embed.embed": (s.block_size, 1, E),
        "trans_head.ln_f.weight": (E,),
        "trans_head.ln_f.bias": (E,),
        "trans_head.head.weight": (s.num_codes, E),
    }
    fused = []
    if s.cross_layers:
        for p in ("weight", "bias"):
            names[f"trans_base.word_emb.{p}"] = f"transformer.word_proj.{p}"
        shapes["trans_base.word_emb.weight"], shapes["trans_base.word_emb.bias"] = (E, s.word_dim), (E,)
    blocks = [
        (f"trans_base.cross_att.{i}", f"transformer.cross_layers.{i}", True) for i in range(s.cross_layers)
    ]
    blocks += [(f"trans_base.blocks.{i}", f"transformer.layers.{i}", False) for i in range(s.base_layers)]
    blocks += [
        (f"trans_head.blocks.{i}", f"transformer.layers.{s.base_layers + i}", False)
        for i in range(s.head_layers)
    ]
    for released, ours, cross in blocks:
        names.update(_block_names(released, ours, cross))
        fused.append((released, ours))
        for ln in ("ln1", "ln2", "ln3") if cross else ("ln1", "ln2"):
            shapes[f"{released}.{ln}.weight"] = shapes[f"{released}.{ln}.bias"] = (E,)
        for proj in ("key", "query", "value", "proj"):
            shapes[f"{released}.attn.{proj}.weight"], shapes[f"{released}.attn.{proj}.bias"] = (E, E), (E,)
        shapes[f"{released}.mlp.0.weight"], shapes[f"{released}.mlp.0.bias"] = (H, E), (H,)
        shapes[f"{released}.mlp.2.weight"], shapes[f"{released}.mlp.2.bias"] = (E, H), (E,)
        if cross:
            shapes[f"{released}.attn.mask"] = (1, 1, s.block_size, CLIP_POSITIONS)
    return names, fused, shapes


def transformer_from_released(
    trans: Mapping[str, torch.Tensor], source: str
) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor], ReleasedTransformerSizes]:
    """(MaskedTransformerModule tensors except the codebook buffer, the embedded stage-1 state dict
    with its `vqvae.` names, sizes) of a released stage-2 state dict."""
    vq = {k[len(VQ_PREFIX) :]: v for k, v in trans.items() if k.startswith(VQ_PREFIX)}
    own = {k: v for k, v in trans.items() if not k.startswith(VQ_PREFIX)}
    sizes = transformer_sizes(own, source)
    names, fused, shapes = _transformer_layout(sizes)
    _check(own, shapes, source, "stage-2 (transformer)")
    table = own["trans_base.pos_embed.embed"].float()[:, 0]
    expected = sinusoidal_positions(sizes.block_size, sizes.embed_dim)
    if not torch.allclose(table, expected, atol=1e-4):
        raise ReleasedKeyError(
            f"{source}: trans_base.pos_embed.embed is not the fixed sinusoidal table the released forward "
            "pass adds "
            f"(max difference {float((table - expected).abs().max()):.3g}); the file was modified"
        )
    state = {ours: own[released].detach().float().clone() for released, ours in names.items()}
    for released, ours in fused:
        for p in ("weight", "bias"):
            key, value = own[f"{released}.attn.key.{p}"], own[f"{released}.attn.value.{p}"]
            state[f"{ours}.attn.kv.{p}"] = torch.cat((key, value)).detach().float().clone()
    return state, vq, sizes


def transformer_to_released(
    state: Mapping[str, torch.Tensor], cfg: TransformerConfig, vq: Mapping[str, torch.Tensor]
) -> dict[str, torch.Tensor]:
    """The released stage-2 state dict (`trans`) of a released-variant MaskedTransformerModule state
    dict and the released stage-1 state dict `vq` (embedded under trans_base.vqvae.). The unused
    learned `pos_embedding` is written as zeros and the unused cross-attention mask as the
    release's lower-triangular one."""
    if cfg.variant != "released":
        raise ValueError(
            "only the released variant has the released layout (its head has no bias, its null text none)"
        )
    # The release stacks num_layers - cross "base" blocks and num_layers "head" blocks.
    half = cfg.num_layers // 2
    if cfg.num_layers % 2 or half < cfg.num_cross_layers:
        raise ValueError(
            f"{cfg.num_layers} layers with {cfg.num_cross_layers} cross layers have no released layout "
            "(it has n - cross base blocks and n head blocks, 2n layers in all)"
        )
    codebook = state["transformer.codebook"]
    word = state.get("transformer.word_proj.weight")
    sizes = ReleasedTransformerSizes(
        embed_dim=cfg.embed_dim,
        code_dim=int(codebook.shape[1]),
        num_codes=int(codebook.shape[0]),
        sentence_dim=int(state["transformer.sentence_proj.weight"].shape[1]),
        word_dim=int(word.shape[1]) if word is not None else 0,
        cross_layers=cfg.num_cross_layers,
        base_layers=half - cfg.num_cross_layers,
        head_layers=half,
        mlp_dim=cfg.mlp_ratio * cfg.embed_dim,
        block_size=cfg.max_tokens + 1,
    )
    names, fused, _ = _transformer_layout(sizes)
    out = {released: state[ours].detach().clone() for released, ours in names.items()}
    E = cfg.embed_dim
    for released, ours in fused:
        for p in ("weight", "bias"):
            key, value = state[f"{ours}.attn.kv.{p}"].split(E)
            out[f"{released}.attn.key.{p}"], out[f"{released}.attn.value.{p}"] = key.clone(), value.clone()
    out["trans_base.pos_embedding.weight"] = torch.zeros(sizes.block_size, E)
    out["trans_base.pos_embed.embed"] = sinusoidal_positions(sizes.block_size, E).unsqueeze(1)
    for i in range(cfg.num_cross_layers):
        out[f"trans_base.cross_att.{i}.attn.mask"] = torch.tril(
            torch.ones(sizes.block_size, CLIP_POSITIONS)
        ).view(1, 1, sizes.block_size, CLIP_POSITIONS)
    out.update({VQ_PREFIX + k: v.detach().clone() for k, v in vq.items()})
    return out
