"""A deterministic paragraph splitter: a long description into short prompts, one per action.

The paper names this as a limitation (supplementary J) and proposes an LLM; a rule-based
splitter is enough for descriptions written as a sequence of actions:

    "A person walks forward, then turns left. After that they jump twice and finally sit down."
    -> ["a person walks forward", "a person turns left", "a person jumps twice", "a person sits down"]

Rules: split at sentence ends (. ! ? ;) and at sequencing words (then, and then, after that,
afterwards, next, finally, followed by, before, later; an "and" before any of them goes too); drop
fillers ("and" at either end, commas) and leading order words ("first,", "lastly"); a fragment
without a subject gets the paragraph's first subject ("a person" by default), and "they"/"he"/"she"
are replaced by it, and the verb is put in the third person ("sitting down" and "sit down" both
give "sits down"); a fragment that is an action noun ("followed by a jump") becomes its verb
("jumps"), another noun phrase is done ("does a cartwheel"); a fragment that starts with a
direction ("... walks up the stairs then down the stairs") repeats the verb before it.
"""

from __future__ import annotations

import re

# "before" only where an action follows ("before sitting down", "before he sits"), not "as before".
_SEQUENCERS = (
    r"(?:then|after that|afterwards|afterward|next|finally|followed by|before that|later|after which"
    r"|before(?=\s+(?:[a-z]+ing|he|she|they|someone|somebody|(?:a|the) (?:person|man|woman|human))\b))"
)
_SPLIT = re.compile(
    rf"[.!?;]+|(?:^|,?\s+)(?:and\s+)?\b{_SEQUENCERS}\b,?\s*|,\s*(?=(?:and\s+)?\b{_SEQUENCERS}\b)",
    re.IGNORECASE,
)
# Words that only order or join the actions: a fragment of nothing else is dropped, and they are
# taken off the start of a fragment ("first, walk forward").
_ORDER = r"(?:and|but|so|first of all|first|firstly|at first|initially|to begin with|lastly|last)"
_FILLER = re.compile(rf"^(?:(?:{_ORDER}|{_SEQUENCERS})\b[\s,]*)+", re.IGNORECASE)
_TRAILING = re.compile(r"(?:[\s,]+(?:and|but|so))+$", re.IGNORECASE)  # "walks to the left and"
# A fragment starting with one of these has no verb of its own: "... then down the stairs".
_DIRECTIONS = {
    "up",
    "down",
    "back",
    "backward",
    "backwards",
    "forward",
    "forwards",
    "left",
    "right",
    "around",
    "away",
    "across",
    "along",
    "over",
    "into",
    "onto",
    "to",
    "toward",
    "towards",
    "sideways",
    "in",
    "out",
}
_SUBJECTS = (
    "a person",
    "the person",
    "someone",
    "a man",
    "the man",
    "a woman",
    "the woman",
    "a human",
    "the human",
    "somebody",
    "he",
    "she",
    "they",
    "it",
)
_PRONOUNS = {"he", "she", "they", "it"}
_PLURAL_VERB = {"are": "is", "do": "does", "have": "has", "go": "goes"}
_ARTICLES = {"a", "an", "the", "one"}
# Nouns of an action that name its verb too: "followed by a jump" -> "jumps".
_ACTION_NOUNS = {
    "jump", "kick", "punch", "wave", "turn", "run", "walk", "spin", "step", "bow", "hop", "squat",
    "lunge", "skip", "stretch", "crouch", "sprint", "jog", "roll", "climb", "dance", "throw", "clap",
    "leap", "stomp", "twist", "swing", "shuffle", "stroll",
}  # fmt: skip
_VOWELS = "aeiou"


def _base_of_gerund(word: str) -> str:
    """The verb of an -ing form: sitting -> sit, waving -> wave, walking -> walk."""
    base = word[:-3]
    if len(base) >= 3 and base[-1] == base[-2] and base[-1] not in _VOWELS + "lsz":
        return base[:-1]  # sitting, running, stepping, jogging (not rolling, kissing, buzzing)
    if base.endswith(("v", "c", "ung")) or (base[-1:] == "s" and base[-2:-1] != "s"):
        return base + "e"  # waving, dancing, lunging, raising, pausing (not crossing)
    if len(base) >= 3 and base[-1] == "l" and base[-2] not in _VOWELS + "l":
        return base + "e"  # circling, shuffling (not rolling, kneeling)
    if (
        3 <= len(base) <= 5
        and base[-1] not in _VOWELS + "wxy"
        and base[-2] in _VOWELS
        and base[-3] not in _VOWELS
        and not base.endswith(("er", "en", "on", "it", "el"))
    ):
        return base + "e"  # making, rotating, gliding (not opening, visiting, entering)
    return base


def _third_person(verb: str) -> str:
    """The third person of a verb, with any punctuation after it kept ("jump," -> "jumps,")."""
    word, tail = re.match(r"([a-z'-]*)(.*)", verb).groups()
    if not word:
        return verb
    if word.endswith("ing") and len(word) > 5:
        word = _base_of_gerund(word)
    if word in _PLURAL_VERB:
        return _PLURAL_VERB[word] + tail
    if word.endswith("s") and not word.endswith("ss"):
        return word + tail
    if word.endswith(("ch", "sh", "x", "ss", "o")):
        return word + "es" + tail
    if word.endswith("y") and len(word) > 1 and word[-2] not in _VOWELS:
        return word[:-1] + "ies" + tail
    return word + "s" + tail


def _predicate(words: list[str]) -> str:
    """A fragment without a subject as what the subject does: the verb in the third person, an
    action noun as its verb ("a jump forward" -> "jumps forward"), another noun phrase done."""
    if words[0] in _ARTICLES and len(words) > 1:
        if words[1].rstrip(",") in _ACTION_NOUNS:
            return " ".join([_third_person(words[1]), *words[2:]])
        return "does " + " ".join(words)
    at = 1 if words[0].endswith("ly") and len(words) > 1 else 0  # "slowly walk" -> "slowly walks"
    return " ".join([*words[:at], _third_person(words[at]), *words[at + 1 :]])


def split_paragraph(paragraph: str, default_subject: str = "a person") -> list[str]:
    """Short prompts, in order, from a paragraph (ValueError when nothing is left)."""
    fragments = [f.strip(" ,") for f in _SPLIT.split(paragraph) if f and f.strip(" ,")]
    subject = default_subject
    prompts = []
    last_verb = "moves"  # for a fragment that only gives a direction
    for fragment in fragments:
        text = re.sub(r"\s+", " ", fragment).strip().lower()
        text = _TRAILING.sub("", _FILLER.sub("", text)).strip(" ,")
        if not text:
            continue
        found = next((s for s in _SUBJECTS if text == s or text.startswith(s + " ")), None)
        if found and found not in _PRONOUNS:
            if not prompts:
                subject = found
        elif found in _PRONOUNS:
            rest = text[len(found) :].strip()
            if rest:
                verb, _, tail = rest.partition(" ")
                text = f"{subject} {_third_person(verb)} {tail}".strip()
            else:
                continue
        elif text.split(" ")[0] in _DIRECTIONS:
            text = f"{subject} {last_verb} {text}"
        else:
            text = f"{subject} {_predicate(text.split(' '))}"
        action = text[len(subject) :].split() if text.startswith(subject + " ") else []
        if action:
            last_verb = action[1] if action[0].endswith("ly") and len(action) > 1 else action[0]
        prompts.append(text)
    if not prompts:
        raise ValueError(
            f"no action found in the paragraph {paragraph!r}; write e.g. 'a person walks forward, then jumps'"
        )
    return prompts
