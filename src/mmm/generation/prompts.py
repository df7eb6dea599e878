"""A deterministic paragraph splitter: a long description into short prompts, one per action.

The paper names this as a limitation (supplementary J) and proposes an LLM; a rule-based
splitter is enough for descriptions written as a sequence of actions:

    "A person walks forward, then turns left. After that they jump twice and finally sit down."
    -> ["a person walks forward", "a person turns left", "a person jumps twice", "a person sits down"]

Rules: split at sentence ends (. ! ? ;) and at sequencing words (then, and then, after that,
afterwards, next, finally, followed by, before, later); drop fillers ("and", leading commas) and
leading order words ("first,", "lastly"); a fragment without a subject gets the paragraph's first
subject ("a person" by default), and "they"/"he"/"she" are replaced by it, and the verb is put in
the third person; a fragment that starts with a direction ("... walks up the stairs then down the
stairs") repeats the verb before it.
"""

from __future__ import annotations

import re

_SEQUENCERS = (
    r"(?:and then|then|after that|afterwards|afterward|next|finally|followed by|before that|later"
    r"|and finally|after which)"
)
_SPLIT = re.compile(rf"[.!?;]+|(?:^|,?\s+)\b{_SEQUENCERS}\b,?\s*|,\s*(?=\b{_SEQUENCERS}\b)", re.IGNORECASE)
# Words that only order or join the actions: a fragment of nothing else is dropped, and they are
# taken off the start of a fragment ("first, walk forward").
_ORDER = r"(?:and|but|so|first of all|first|firstly|at first|initially|to begin with|lastly|last)"
_FILLER = re.compile(rf"^(?:(?:{_ORDER}|{_SEQUENCERS})\b[\s,]*)+", re.IGNORECASE)
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


def _third_person(verb: str) -> str:
    if verb in _PLURAL_VERB:
        return _PLURAL_VERB[verb]
    if verb.endswith("s") and not verb.endswith("ss"):
        return verb
    if verb.endswith(("ch", "sh", "x", "ss", "o")):
        return verb + "es"
    if verb.endswith("y") and len(verb) > 1 and verb[-2] not in "aeiou":
        return verb[:-1] + "ies"
    return verb + "s"


def split_paragraph(paragraph: str, default_subject: str = "a person") -> list[str]:
    """Short prompts, in order, from a paragraph (ValueError when nothing is left)."""
    fragments = [f.strip(" ,") for f in _SPLIT.split(paragraph) if f and f.strip(" ,")]
    subject = default_subject
    prompts = []
    last_verb = "moves"  # for a fragment that only gives a direction
    for fragment in fragments:
        text = re.sub(r"\s+", " ", fragment).strip().lower()
        text = _FILLER.sub("", text).strip(" ,")
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
            words = text.split(" ")
            at = 1 if words[0].endswith("ly") and len(words) > 1 else 0  # "slowly walk" -> "slowly walks"
            words[at] = _third_person(words[at])
            text = f"{subject} {' '.join(words)}"
        action = text[len(subject) :].split() if text.startswith(subject + " ") else []
        if action:
            last_verb = action[1] if action[0].endswith("ly") and len(action) > 1 else action[0]
        prompts.append(text)
    if not prompts:
        raise ValueError(
            f"no action found in the paragraph {paragraph!r}; write e.g. 'a person walks forward, then jumps'"
        )
    return prompts
