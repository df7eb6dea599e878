"""Counterfactual captions: a caption with one countable detail changed ("jumps twice" ->
"jumps three times", "walks slowly" -> "walks quickly").

`counterfactual_captions` rewrites the count ("once", "twice", "thrice", "<n> times", "<n> jumps")
to each other count up to four, and a speed word to one of the opposite speed, one change per
variant, keeping the rest of the caption as written. Plain English patterns, so they apply to any
dataset's captions; a caption without a count or speed word has no counterfactual. Their uses:
the evaluator's hard negatives (`loss.counterfactuals`), its test of whether it reads counts and
speeds (mmm.evaluation.counterfactuals), and best of N's margins (mmm.generation.best_of).
"""

from __future__ import annotations

import re

MAX_COUNT = 4
_COUNT_WORDS = {"one": 1, "two": 2, "three": 3, "four": 4, "five": 5, "six": 6}
_NUMBER_WORDS = {n: w for w, n in _COUNT_WORDS.items()}
_ADVERBS = {"once": 1, "twice": 2, "thrice": 3}
_COUNT = re.compile(
    r"\b(?:(?P<adverb>once|twice|thrice)|(?P<number>one|two|three|four|five|six|\d)\s+times?)\b",
    re.IGNORECASE,
)
# "three jumps", "2 squats": a number before a plural noun; changed among two to four only (a
# singular would need the noun's singular form).
_PLURAL = re.compile(
    r"\b(?P<number>two|three|four|five|six|[2-6])\s+(?!times\b)(?P<noun>[a-z]+s)\b", re.IGNORECASE
)
# Each speed word and what it becomes at the opposite speed (adverb to adverb, adjective to adjective).
_OPPOSITE_SPEED = {
    "slowly": "quickly",
    "slow": "fast",
    "leisurely": "briskly",
    "quickly": "slowly",
    "quick": "slow",
    "fast": "slow",
    "briskly": "leisurely",
    "rapidly": "slowly",
    "swiftly": "slowly",
    "hurriedly": "slowly",
}
_SPEED = re.compile(r"\b(" + "|".join(_OPPOSITE_SPEED) + r")\b", re.IGNORECASE)


def _count_of(match: re.Match) -> int:
    if match["adverb"]:
        return _ADVERBS[match["adverb"].lower()]
    number = match["number"].lower()
    return int(number) if number.isdigit() else _COUNT_WORDS[number]


def _spell_count(n: int, digits: bool) -> str:
    """How many times, written as the caption wrote it: digits stay digits ("2 times"); one is
    always "once" ("1 times" is not English)."""
    if n == 1:
        return "once"
    if digits:
        return f"{n} times"
    return {2: "twice"}.get(n, f"{_NUMBER_WORDS[n]} times")


def _match_case(word: str, like: str) -> str:
    return word.capitalize() if like[:1].isupper() else word


KINDS = ("count", "speed")


def counterfactual_captions(caption: str, kinds: tuple[str, ...] = KINDS) -> list[str]:
    """The caption with one count or speed word changed, each variant once, in the order found.

    "a person jumps twice" -> ["a person jumps once", "a person jumps three times", "a person jumps
    four times"]; "walks slowly" -> ["walks quickly"]. Counts above MAX_COUNT are left alone (no
    variant of "jumps six times"): the data rarely holds them. `kinds` picks the changes.
    """
    unknown = set(kinds) - set(KINDS)
    if unknown:
        raise ValueError(f"counterfactual kinds {sorted(unknown)} are not among {list(KINDS)}")
    variants: dict[str, None] = {}
    for match in _COUNT.finditer(caption) if "count" in kinds else ():
        n = _count_of(match)
        if n > MAX_COUNT:
            continue
        digits = bool(match["number"]) and match["number"].isdigit()
        for m in range(1, MAX_COUNT + 1):
            if m != n:
                spelled = _match_case(_spell_count(m, digits), match[0])
                variants[caption[: match.start()] + spelled + caption[match.end() :]] = None
    for match in _PLURAL.finditer(caption) if "count" in kinds else ():
        number = match["number"].lower()
        n = int(number) if number.isdigit() else _COUNT_WORDS[number]
        if n > MAX_COUNT:
            continue
        for m in range(2, MAX_COUNT + 1):
            if m != n:
                spelled = _match_case(str(m) if number.isdigit() else _NUMBER_WORDS[m], match["number"])
                variants[caption[: match.start()] + spelled + caption[match.end("number") :]] = None
    for match in _SPEED.finditer(caption) if "speed" in kinds else ():
        opposite = _match_case(_OPPOSITE_SPEED[match[0].lower()], match[0])
        variants[caption[: match.start()] + opposite + caption[match.end() :]] = None
    variants.pop(caption, None)
    return list(variants)
