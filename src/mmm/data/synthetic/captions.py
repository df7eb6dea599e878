"""Captions of the synthetic clips: paraphrased templates, part-of-speech tokens, mirroring.

Each action's verb phrases are in its spec (table.py); here they get a subject, are chained for
composites and tagged.

A caption line is `caption#word/POS word/POS ...#start#end` (motion-format.md). Tokens are
lower-case lemmas with universal POS tags from the small built-in LEXICON; every word of a
caption gets exactly one token. Templates write `word|TAG` where a word's tag differs from its
default (e.g. "steps|NOUN" in "takes slow steps", "steps|VERB" in "steps backwards").
"""

from __future__ import annotations

import re

import numpy as np

from mmm.data.synthetic.constants import FPS
from mmm.data.synthetic.table import ACTIONS, pick

# word -> (lemma, default tag)
LEXICON: dict[str, tuple[str, str]] = {}


def _lex(tag: str, words: str) -> None:
    for item in words.split():
        word, _, lemma = item.partition(":")
        LEXICON[word] = (lemma or word, tag)


_lex("DET", "a the an his her their both every each all")
_lex("PRON", "someone something it them he she they himself herself themselves")
_lex(
    "NOUN",
    "person man woman human figure circle direction hand:hand hands:hand arm:arm arms:arm "
    "foot feet:foot leg legs:leg fist fists:fist head air side chair seat knees:knee knee "
    "degrees:degree times:time time jump jumps:jump squat squats:squat step:step steps:step "
    "kick punch punches:punch turn pace spot place line way hips:hip shoulder chest "
    "front balance motion wave sides:side",
)
_lex(
    "VERB",
    "walks:walk walking:walk moves:move moving:move steps:step takes:take runs:run running:run "
    "jogs:jog jogging:jog turns:turn turning:turn rotates:rotate pivots:pivot makes:make "
    "circles:circle goes:go jumps:jump hops:hop leaps:leap does:do performs:perform "
    "squats:squat bends:bend lowers:lower stands:stand standing:stand waves:wave waving:wave "
    "raises:raise lifts:lift puts:put holds:hold kicks:kick punches:punch throws:throw "
    "boxes:box sits:sit gets:get stays:stay remains:remain waits:wait strolls:stroll "
    "hurries:hurry shuffles:shuffle sidesteps:sidestep face:face rises:rise strides:stride "
    "dashes:dash completes:complete swings:swing spins:spin keeps:keep",
)
_lex("AUX", "is")
_lex(
    "ADV",
    "forward forwards backward backwards ahead straight slowly quickly fast briskly rapidly "
    "leisurely steadily gently sideways around once twice thrice then afterwards first up down "
    "back still again clockwise counterclockwise anticlockwise left right alternately briefly "
    "repeatedly together",
)
_lex(
    "ADJ",
    "slow quick brisk hurried steady normal regular full single half quarter big small "
    "same other opposite left:left right:right front short long",
)
_lex("ADP", "to toward towards in on at with without of over above into onto before after by from")
_lex("NUM", "one two three 90 180 ninety 2 3")
_lex("CCONJ", "and or")
_lex("PART", "not")
# Words whose default differs by use are written word|TAG in templates (left|ADJ etc.).
TAGS = {"NOUN", "VERB", "ADV", "ADJ", "DET", "ADP", "NUM", "PRON", "CCONJ", "PART", "AUX"}

SUBJECTS = [
    ("a person", "their"),
    ("someone", "their"),
    ("the person", "their"),
    ("a man", "his"),
    ("the man", "his"),
    ("a woman", "her"),
    ("the woman", "her"),
    ("a human", "their"),
    ("a figure", "their"),
]


def _vp(rng: np.random.Generator, action: str, params: dict, stands_up: bool = False) -> str:
    """A verb phrase for one part, from its action's spec; '{pron}' marks the possessive.

    stands_up: for sit, the person gets up again at the end of the part."""
    spec = ACTIONS.get(action)
    if spec is None:
        raise ValueError(f"no captions for action {action!r}")
    return spec.phrase(rng, params, stands_up)


_CONNECTORS = [
    "{a} and then {b}",
    "{a} then {b}",
    "first {a} and then {b}",
    "{a} and afterwards {b}",
    "{a} and {b}",
]
_REFLEXIVE = {"his": "himself", "her": "herself", "their": "themselves"}


def _fill(text: str, pron: str) -> str:
    text = text.replace("{pron}self", _REFLEXIVE[pron])
    return text.replace("{pron}", pron)


def tag_caption(marked: str) -> tuple[str, str]:
    """Caption text and its `lemma/TAG` tokens from a template-filled string (words may carry |TAG)."""
    words, tokens = [], []
    items = marked.split()
    for i, item in enumerate(items):
        word, _, tag = item.partition("|")
        if word == "a" and i + 1 < len(items) and items[i + 1][0] in "aeiou":
            word = "an"
        entry = LEXICON.get(word)
        if entry is None:
            raise KeyError(f"word {word!r} is not in the caption lexicon")
        lemma, default = entry
        tag = tag or default
        if tag not in TAGS:
            raise ValueError(f"unknown tag {tag!r} for {word!r}")
        words.append(word)
        tokens.append(f"{lemma}/{tag}")
    return " ".join(words), " ".join(tokens)


def seconds(frame: int) -> str:
    """Shortest decimal string s with int(float(s) * FPS) == frame."""
    for digits in (1, 2, 3, 4):
        s = f"{frame / FPS:.{digits}f}"
        if int(float(s) * FPS) == frame:
            return s
    s = f"{(frame + 1e-3) / FPS:.5f}"
    assert int(float(s) * FPS) == frame
    return s


def caption_line(marked: str, start: int | None = None, end: int | None = None) -> str:
    """`caption#tokens#start#end`; whole clip (0.0#0.0) when start/end are None (frames otherwise)."""
    text, tokens = tag_caption(marked)
    span = "0.0#0.0" if start is None else f"{seconds(start)}#{seconds(end)}"
    return f"{text}#{tokens}#{span}"


def _whole_clip_lines(
    rng: np.random.Generator, parts: list[dict], stands_up: list[bool], count: int, seen: set[str], tries: int
) -> list[str]:
    """Up to `count` new paraphrases of the whole clip (not in `seen`, which grows), in `tries` draws."""
    lines: list[str] = []
    for _ in range(tries):
        subj, pron = pick(rng, SUBJECTS)
        vps = [_fill(_vp(rng, p["action"], p["params"], up), pron) for p, up in zip(parts, stands_up)]
        body = vps[0] if len(vps) == 1 else pick(rng, _CONNECTORS).format(a=vps[0], b=vps[1])
        line = caption_line(f"{subj} {body}")
        if line not in seen:
            seen.add(line)
            lines.append(line)
        if len(lines) == count:
            break
    return lines


def clip_captions(
    rng: np.random.Generator, parts: list[dict], stands_up: list[bool] | None = None
) -> list[str]:
    """Three paraphrased whole-clip caption lines, plus for a composite one or two lines per part
    with its own #start#end (seconds). parts: label parts (action, params, start, end frames);
    stands_up: per part, whether a sit part ends standing up again."""
    stands_up = stands_up or [False] * len(parts)
    lines = _whole_clip_lines(rng, parts, stands_up, 3, set(), tries=30)
    if len(parts) > 1:
        for p, up in zip(parts, stands_up):
            for _ in range(1 + int(rng.integers(2))):
                subj, pron = pick(rng, SUBJECTS)
                vp = _fill(_vp(rng, p["action"], p["params"], up), pron)
                lines.append(caption_line(f"{subj} {vp}", p["start"], p["end"]))
    return lines


def extra_paraphrases(
    rng: np.random.Generator, parts: list[dict], stands_up: list[bool], count: int, existing: list[str]
) -> list[str]:
    """Up to `count` more whole-clip paraphrases, none equal to a line of `existing`; fewer when
    the templates of these actions have no more (a single "runs once" has only so many)."""
    return _whole_clip_lines(rng, parts, stands_up, count, set(existing), tries=10 * count)


_SWAP = {
    "left": "right",
    "right": "left",
    "clockwise": "counterclockwise",
    "counterclockwise": "clockwise",
    "anticlockwise": "clockwise",
}
_SWAP_RE = re.compile(r"\b(" + "|".join(_SWAP) + r")\b")


def mirror_caption_line(line: str) -> str:
    """Swap left/right and clockwise/counter-clockwise in the caption and its tokens."""
    text, tokens, start, end = line.split("#")
    text = _SWAP_RE.sub(lambda m: _SWAP[m.group(1)], text)
    out = []
    for tok in tokens.split():
        lemma, _, tag = tok.rpartition("/")
        out.append(f"{_SWAP.get(lemma, lemma)}/{tag}")
    return f"{text}#{' '.join(out)}#{start}#{end}"


_PARAM_SWAP = {
    "left": "right",
    "right": "left",
    "clockwise": "counterclockwise",
    "counterclockwise": "clockwise",
}


def mirror_params(params: dict) -> dict:
    """Label parameters of the left/right mirrored motion."""
    return {k: (_PARAM_SWAP.get(v, v) if isinstance(v, str) else v) for k, v in params.items()}


__all__ = [
    "LEXICON",
    "TAGS",
    "caption_line",
    "clip_captions",
    "extra_paraphrases",
    "mirror_caption_line",
    "mirror_params",
    "seconds",
    "tag_caption",
]
