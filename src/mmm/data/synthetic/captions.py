"""Captions of the synthetic clips: paraphrased templates, part-of-speech tokens, mirroring.

A caption line is `caption#word/POS word/POS ...#start#end` (motion-format.md). Tokens are
lower-case lemmas with universal POS tags from the small built-in LEXICON; every word of a
caption gets exactly one token. Templates write `word|TAG` where a word's tag differs from its
default (e.g. "steps|NOUN" in "takes slow steps", "steps|VERB" in "steps backwards").
"""

from __future__ import annotations

import re

import numpy as np

FPS = 20.0

# word -> (lemma, default tag)
LEXICON: dict[str, tuple[str, str]] = {}


def _lex(tag: str, words: str) -> None:
    for item in words.split():
        word, _, lemma = item.partition(":")
        LEXICON[word] = (lemma or word, tag)


_lex("DET", "a the an his her their both every each all")
_lex("PRON", "someone something it them he she they himself herself themselves")
_lex("NOUN", "person man woman human figure circle direction hand:hand hands:hand arm:arm arms:arm "
             "foot feet:foot leg legs:leg fist fists:fist head air side chair seat knees:knee knee "
             "degrees:degree times:time time jump jumps:jump squat squats:squat step:step steps:step "
             "kick punch punches:punch turn pace spot place line way hips:hip shoulder chest "
             "front balance motion wave sides:side")
_lex("VERB", "walks:walk walking:walk moves:move moving:move steps:step takes:take runs:run running:run "
             "jogs:jog jogging:jog turns:turn turning:turn rotates:rotate pivots:pivot makes:make "
             "circles:circle goes:go jumps:jump hops:hop leaps:leap does:do performs:perform "
             "squats:squat bends:bend lowers:lower stands:stand standing:stand waves:wave waving:wave "
             "raises:raise lifts:lift puts:put holds:hold kicks:kick punches:punch throws:throw "
             "boxes:box sits:sit gets:get stays:stay remains:remain waits:wait strolls:stroll "
             "hurries:hurry shuffles:shuffle sidesteps:sidestep face:face rises:rise strides:stride "
             "dashes:dash completes:complete swings:swing spins:spin keeps:keep")
_lex("AUX", "is")
_lex("ADV", "forward forwards backward backwards ahead straight slowly quickly fast briskly rapidly "
            "leisurely steadily gently sideways around once twice thrice then afterwards first up down "
            "back still again clockwise counterclockwise anticlockwise left right alternately briefly "
            "repeatedly together")
_lex("ADJ", "slow quick brisk hurried steady normal regular full single half quarter big small "
            "same other opposite left:left right:right front short long")
_lex("ADP", "to toward towards in on at with without of over above into onto before after by from")
_lex("NUM", "one two three 90 180 ninety 2 3")
_lex("CCONJ", "and or")
_lex("PART", "not")
# Words whose default differs by use are written word|TAG in templates (left|ADJ etc.).
TAGS = {"NOUN", "VERB", "ADV", "ADJ", "DET", "ADP", "NUM", "PRON", "CCONJ", "PART", "AUX"}

SUBJECTS = [("a person", "their"), ("someone", "their"), ("the person", "their"), ("a man", "his"),
            ("the man", "his"), ("a woman", "her"), ("the woman", "her"), ("a human", "their"),
            ("a figure", "their")]

_SPEED_ADV = {
    "slow": ["slowly", "at a slow pace", "leisurely", "slowly and steadily"],
    "normal": ["", "", "at a normal pace", "at a steady pace", "at a regular pace", "steadily"],
    "fast": ["quickly", "fast", "briskly", "at a fast|ADJ pace", "rapidly", "at a quick pace"],
}
_SPEED_PRE = {"slow": ["slowly"], "normal": ["steadily", ""], "fast": ["quickly", "briskly", "rapidly"]}
_SPEED_ADJ = {"slow": ["slow", "short slow"], "normal": ["steady", "regular", "normal"], "fast": ["quick", "fast", "brisk", "hurried"]}
_COUNT_ADV = {1: ["once", "one time", "a single time"], 2: ["twice", "two times", "2 times"],
              3: ["three times", "3 times", "thrice"]}
_COUNT_NOUN = {1: ["a single {n}", "one {n}", "a {n}"], 2: ["two {n}s", "2 {n}s"], 3: ["three {n}s", "3 {n}s"]}


def _pick(rng: np.random.Generator, options):
    return options[int(rng.integers(len(options)))]


def _walk_vp(rng, params):
    d, s = params["direction"], params["speed"]
    adv, pre, adj = _pick(rng, _SPEED_ADV[s]), _pick(rng, _SPEED_PRE[s]), _pick(rng, _SPEED_ADJ[s])
    if d == "forward":
        opts = ["walks forward {adv}", "walks straight ahead {adv}", "{pre} walks forward", "takes {adj} steps|NOUN forward",
                "walks forwards {adv}", "moves forward {adv} on foot", "walks ahead in a straight|ADJ line {adv}"]
        if s == "slow":
            opts.append("strolls forward slowly")
        if s == "fast":
            opts += ["hurries forward", "strides forward quickly"]
    elif d == "backward":
        opts = ["walks backward {adv}", "walks backwards {adv}", "{pre} walks backwards", "steps|VERB back|ADV {adv}",
                "takes {adj} steps|NOUN backward", "moves backward {adv}", "steps|VERB backwards {adv}"]
    else:
        opts = ["walks to the {side}|NOUN {adv}", "sidesteps to the {side}|NOUN {adv}", "steps|VERB sideways to the {side}|NOUN {adv}",
                "{pre} walks sideways to {pron} {side}|NOUN", "shuffles sideways towards the {side}|NOUN {adv}",
                "moves to the {side}|NOUN {adv} with side|NOUN steps|NOUN", "takes {adj} side|NOUN steps|NOUN to the {side}|NOUN"]
    return _pick(rng, opts).format(adv=adv, pre=pre, adj=adj, side=d, pron="{pron}")


def _vp(rng: np.random.Generator, action: str, params: dict, stands_up: bool = False) -> str:
    """A verb phrase (third person, present) for one part; '{pron}' marks the possessive.

    stands_up: for sit, the person gets up again at the end of the part."""
    if action == "stand":
        return _pick(rng, ["stands still", "stands in place", "stands without moving", "is standing still",
                           "remains standing in place", "stays still", "waits standing in one spot",
                           "stands still with {pron} arms at {pron} sides|NOUN"])
    if action == "walk":
        return _walk_vp(rng, params)
    if action == "run":
        return _pick(rng, ["runs forward", "runs straight ahead", "jogs forward", "is running forward",
                           "runs forward quickly", "runs ahead", "dashes forward", "jogs straight ahead"])
    if action == "turn":
        side, angle = params["side"], int(params["angle"])
        if angle == 90:
            opts = ["turns {s}|ADV", "turns to the {s}|NOUN", "turns ninety degrees to the {s}|NOUN", "turns 90 degrees to {pron} {s}|NOUN",
                    "makes a quarter turn|NOUN to the {s}|NOUN", "rotates to {pron} {s}|NOUN", "pivots to the {s}|NOUN"]
        else:
            opts = ["turns around to the {s}|NOUN", "turns 180 degrees to the {s}|NOUN", "makes a half turn|NOUN to the {s}|NOUN",
                    "turns all the way around to {pron} {s}|NOUN", "turns around over {pron} {s}|ADJ shoulder",
                    "turns around to the {s}|NOUN to|PART face the other way"]
        return _pick(rng, opts).format(s=side, pron="{pron}")
    if action == "circle":
        side = params["side"]
        word = side if side == "clockwise" else _pick(rng, ["counterclockwise", "anticlockwise"])
        opts = ["walks in a {w}|ADJ circle", "walks around in a circle {w}|ADV", "walks {w}|ADV in a circle",
                "goes around in a {w}|ADJ circle", "walks a full circle {w}|ADV", "circles around {w}|ADV",
                "walks in a circle in a {w}|ADJ direction"]
        return _pick(rng, opts).format(w=word)
    if action == "jump":
        count, mode = int(params["count"]), params["mode"]
        times = _pick(rng, _COUNT_ADV[count])
        jumps = _pick(rng, _COUNT_NOUN[count]).format(n="jump")
        if mode == "in_place":
            where = _pick(rng, ["in place", "on the spot", "in the same spot", "up|ADV and down|ADV"])
            opts = ["jumps {where} {times}", "jumps {times} {where}", "hops {where} {times}", "does {jumps} {where}",
                    "jumps up|ADV {times}"]
        else:
            where = _pick(rng, ["forward", "forwards", "ahead"])
            opts = ["jumps {where} {times}", "jumps {times} {where}", "hops {where} {times}", "leaps {where} {times}",
                    "does {jumps} {where}", "makes {jumps} {where}"]
        return _pick(rng, opts).format(where=where, times=times, jumps=jumps)
    if action == "squat":
        count = int(params["count"])
        times = _pick(rng, _COUNT_ADV[count])
        squats = _pick(rng, _COUNT_NOUN[count]).format(n="squat")
        return _pick(rng, ["squats {times}", "squats down {times}", "does {squats}", "performs {squats}",
                           "bends {pron} knees and squats {times}", "squats down and stands|VERB back|ADV up|ADV {times}"]).format(
            times=times, squats=squats, pron="{pron}")
    if action == "wave":
        hand = params["hand"]
        if hand == "both":
            return _pick(rng, ["waves both hands", "waves with both arms", "raises both hands and waves them",
                               "waves both arms over {pron} head", "waves with both hands above {pron} head"])
        return _pick(rng, ["waves {pron} {h}|ADJ hand", "waves with {pron} {h}|ADJ hand", "raises {pron} {h}|ADJ hand and waves",
                           "waves the {h}|ADJ arm above {pron} head", "lifts the {h}|ADJ hand and waves it"]).format(h=hand, pron="{pron}")
    if action == "raise_arms":
        return _pick(rng, ["raises both arms", "raises {pron} arms above {pron} head", "lifts {pron} arms up|ADV",
                           "puts {pron} hands up|ADV in the air", "raises {pron} hands over {pron} head",
                           "holds {pron} arms up|ADV above {pron} head", "lifts both arms into the air"])
    if action == "kick":
        f = params["foot"]
        return _pick(rng, ["kicks with {pron} {f}|ADJ foot", "kicks forward with the {f}|ADJ leg", "does a kick|NOUN with {pron} {f}|ADJ leg",
                           "kicks {pron} {f}|ADJ leg forward", "performs a front|ADJ kick|NOUN with the {f}|ADJ foot",
                           "kicks something in front|NOUN with {pron} {f}|ADJ foot"]).format(f=f, pron="{pron}")
    if action == "punch":
        hand = params["hand"]
        if hand == "both":
            return _pick(rng, ["punches with both hands", "throws punches|NOUN with both fists", "punches forward with both arms alternately",
                               "boxes with both hands", "throws punches|NOUN with {pron} left|ADJ and right|ADJ fists"])
        return _pick(rng, ["punches forward with {pron} {h}|ADJ hand", "throws a punch|NOUN with {pron} {h}|ADJ fist",
                           "punches with the {h}|ADJ arm", "punches straight ahead with {pron} {h}|ADJ fist",
                           "throws punches|NOUN with the {h}|ADJ hand"]).format(h=hand, pron="{pron}")
    if action == "sit":
        if stands_up:
            return _pick(rng, ["sits down on a chair and gets back|ADV up|ADV", "sits down briefly and stands|VERB up|ADV again",
                               "takes a seat and stands|VERB up|ADV again", "sits on a chair and then rises",
                               "sits down and stands|VERB back|ADV up|ADV"])
        return _pick(rng, ["sits down", "sits down on a chair", "takes a seat", "sits on a chair", "lowers {pron}self onto a seat|NOUN"])
    raise ValueError(f"no captions for action {action!r}")


_CONNECTORS = ["{a} and then {b}", "{a} then {b}", "first {a} and then {b}", "{a} and afterwards {b}", "{a} and {b}"]
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


def clip_captions(rng: np.random.Generator, parts: list[dict], stands_up: list[bool] | None = None) -> list[str]:
    """Three paraphrased whole-clip caption lines, plus for a composite one or two lines per part
    with its own #start#end (seconds). parts: label parts (action, params, start, end frames);
    stands_up: per part, whether a sit part ends standing up again."""
    stands_up = stands_up or [False] * len(parts)
    lines, seen = [], set()
    for _ in range(30):
        subj, pron = _pick(rng, SUBJECTS)
        vps = [_fill(_vp(rng, p["action"], p["params"], up), pron) for p, up in zip(parts, stands_up)]
        body = vps[0] if len(vps) == 1 else _pick(rng, _CONNECTORS).format(a=vps[0], b=vps[1])
        line = caption_line(f"{subj} {body}")
        if line not in seen:
            seen.add(line)
            lines.append(line)
        if len(lines) == 3:
            break
    if len(parts) > 1:
        for p, up in zip(parts, stands_up):
            for _ in range(1 + int(rng.integers(2))):
                subj, pron = _pick(rng, SUBJECTS)
                vp = _fill(_vp(rng, p["action"], p["params"], up), pron)
                lines.append(caption_line(f"{subj} {vp}", p["start"], p["end"]))
    return lines


_SWAP = {"left": "right", "right": "left", "clockwise": "counterclockwise", "counterclockwise": "clockwise",
         "anticlockwise": "clockwise"}
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


_PARAM_SWAP = {"left": "right", "right": "left", "clockwise": "counterclockwise", "counterclockwise": "clockwise"}


def mirror_params(params: dict) -> dict:
    """Label parameters of the left/right mirrored motion."""
    return {k: (_PARAM_SWAP.get(v, v) if isinstance(v, str) else v) for k, v in params.items()}


__all__ = ["LEXICON", "TAGS", "caption_line", "clip_captions", "mirror_caption_line", "mirror_params", "seconds", "tag_caption"]
