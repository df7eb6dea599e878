"""A deterministic paragraph splitter: a long description into short prompts, one per action, in
the order the actions happen.

The paper names this as a limitation (supplementary J) and proposes an LLM; a rule-based
splitter is enough for descriptions written as a sequence of actions:

    "A person walks forward, then turns left. After that they jump twice and finally sit down."
    -> ["a person walks forward", "a person turns left", "a person jumps twice", "a person sits down"]
    "The man jumps after walking forward. Before sitting down, he waves."
    -> ["the man walks forward", "the man jumps", "the man waves", "the man sits down"]

Rules, sentence by sentence (. ! ? ;):
- split at sequencing words (then, and then, after that, afterwards, next, finally, followed by,
  later, "ends by", and "before" where an action follows it; an "and" before any of them goes too);
- "after/once/when/as soon as X, Y" gives X then Y, "before X, Y" gives Y then X, "Y after X" gives
  X then Y; an X without an action ("once done", "after a while") is dropped; a sentence that starts
  "Before that," goes before the one ahead of it;
- a list of verb phrases ("walk forward, turn around and walk back") gives one prompt per phrase; a
  lone "A and B" stays one prompt (it may be one motion: "walks and waves") unless B has its own
  subject ("and he sits down");
- fillers go: "and" at either end, commas, order words ("first,", "second,", "lastly", "starts by");
- each prompt gets the paragraph's first named subject ("a person" by default) in place of a
  missing one or of "they"/"he"/"she", with its verbs in the third person ("sitting down" and "sit
  down" both give "sits down", "turn and walk back" gives "turns and walks back"); an action noun
  becomes its verb ("followed by a jump" -> "jumps"), another noun phrase is done ("does a
  cartwheel"); a fragment that starts with a direction, a possessive or a side ("... walks up the
  stairs then down the stairs", "lifts the left knee, then the right knee") repeats the verb before
  it.
"""

from __future__ import annotations

import re

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
# Who can start a clause after "before"/"after ..." without a comma ("after walking he jumps"): not
# "it", which is as often an object ("after lifting it").
_PEOPLE = "|".join(s for s in _SUBJECTS if s != "it")
# "before" only where an action follows ("before sitting down", "before he sits"), not "as before";
# at the start of a sentence it opens a clause instead ("Before sitting down, he waves").
_BEFORE = rf"before(?=\s+(?:[a-z]+ing|{_PEOPLE})\b)"
_SEQUENCERS = (
    r"(?:then|after that|afterwards|afterward|next|finally|followed by|later|after which"
    r"|(?:ends?|finish(?:es)?) (?:by|with))"
)
_SPLIT = re.compile(
    rf"(?:^|,?\s+)(?:and\s+)?\b{_SEQUENCERS}\b,?\s*|,?\s+(?:and\s+)?\b{_BEFORE}\s*"
    rf"|,\s*(?=(?:and\s+)?\b(?:{_SEQUENCERS}|{_BEFORE})\b)",
    re.IGNORECASE,
)
# Words that only order or join the actions: a fragment of nothing else is dropped, and they are
# taken off the start of a fragment ("first, walk forward", "he starts by walking").
_ORDER = (
    r"(?:and|but|so|first of all|first|firstly|at first|initially|to begin with|second|secondly|third"
    r"|thirdly|lastly|last|subsequently|eventually|(?:starts?|begins?|starting|beginning) (?:by|with))"
)
_FILLER = re.compile(rf"^(?:(?:{_ORDER}|{_SEQUENCERS}|{_BEFORE})\b[\s,]*)+", re.IGNORECASE)
_TRAILING = re.compile(r"(?:[\s,]+(?:and|but|so))+$", re.IGNORECASE)  # "walks to the left and"
# A clause that says when the rest happens: "After walking forward, he jumps".
_WHEN = rf"^(?:{_ORDER}\b[\s,]*)*(after|before|once|when|as soon as)\s+"
_LEADING_CLAUSE = (
    re.compile(rf"{_WHEN}([^,]+?)\s*,\s*(.+)$", re.IGNORECASE),
    re.compile(rf"{_WHEN}(.+?)\s+((?:{_PEOPLE})\b.+)$", re.IGNORECASE),
)
# "Before that" puts what follows before what came ahead of it (in the sentence, or the one before).
_BEFORE_THAT = re.compile(r"(?:^|,?\s+)before (?:that|this|then)\b[\s,]*", re.IGNORECASE)
# A fragment starting with one of these (or a possessive, or a side) has no verb of its own: "...
# then down the stairs".
_DIRECTIONS = {
    "up", "down", "back", "backward", "backwards", "forward", "forwards", "left", "right", "around",
    "away", "across", "along", "over", "into", "onto", "to", "toward", "towards", "sideways", "in",
    "out",
}  # fmt: skip
_POSSESSIVES = {"his", "her", "their"}  # "... raises his left arm, then his right arm"
_SIDES = ("the left ", "the right ", "the other ", "the opposite ", "both ")  # "..., then the right knee"
_PLURAL_VERB = {"are": "is", "do": "does", "have": "has", "go": "goes"}
_ARTICLES = {"a", "an", "the", "one"}
_COUNTS = {"two", "three", "four", "five", "six", "seven", "eight", "nine", "ten", "few", "several", "some"}
# Nouns of an action that name its verb too: "followed by a jump" -> "jumps".
_ACTION_NOUNS = {
    "jump", "kick", "punch", "wave", "turn", "run", "walk", "spin", "step", "bow", "hop", "squat",
    "lunge", "skip", "stretch", "crouch", "sprint", "jog", "roll", "climb", "dance", "throw", "clap",
    "leap", "stomp", "twist", "swing", "shuffle", "stroll",
}  # fmt: skip
# Verbs of motion: what tells a phrase that does something ("turn around") from one that describes
# ("arms raised", "a while"), in lists and clauses.
_MOTION_VERBS = _ACTION_NOUNS | {
    "sit", "stand", "rise", "get", "kneel", "bend", "lean", "lie", "crawl", "march", "tiptoe",
    "limp", "stagger", "stumble", "raise", "lift", "lower", "reach", "catch", "push", "pull", "pick",
    "put", "place", "grab", "hold", "carry", "shake", "nod", "slide", "fall", "dodge", "duck",
    "salute", "point", "move", "go", "come", "return", "stop", "pause", "rest", "wait", "look",
    "sway", "bounce", "balance", "stride", "pace", "swim", "circle", "rotate", "cross", "extend",
    "drop", "do", "perform", "take", "make", "play", "bring", "open", "wipe", "touch", "flap", "hug",
    "clean", "drink", "eat", "stir", "sweep", "paddle", "row", "fight", "box", "swat", "celebrate",
    "exercise", "skate", "ski", "pivot",
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


def _motion_verb(word: str) -> str | None:
    """The base form when `word` is a motion verb in any form (walk, walks, walking), else None."""
    word = word.strip(",").lower()
    if word.endswith("ing") and len(word) > 5:
        word = _base_of_gerund(word)
    candidates = [word]
    if word.endswith("ies"):
        candidates.append(word[:-3] + "y")
    elif word.endswith("es"):
        candidates += [word[:-1], word[:-2]]
    elif word.endswith("s"):
        candidates.append(word[:-1])
    return next((c for c in candidates if c in _MOTION_VERBS), None)


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
    """Words without a subject as what the subject does: the verbs in the third person (the first
    and any after "and": "turn and walk back" -> "turns and walks back"), an action noun as its verb
    ("a jump forward" -> "jumps forward"), another noun phrase done."""
    if words[0] in _ARTICLES | _COUNTS and len(words) > 1:
        if words[0] in _ARTICLES and words[1].rstrip(",") in _ACTION_NOUNS:
            return " ".join([_third_person(words[1]), *words[2:]])
        return "does " + " ".join(words)
    words = list(words)
    at = 1 if words[0].endswith("ly") and len(words) > 1 else 0  # "slowly walk" -> "slowly walks"
    words[at] = _third_person(words[at])
    for i in range(at + 1, len(words) - 1):
        if words[i] in ("and", "or"):
            j = i + 2 if words[i + 1].endswith("ly") and i + 2 < len(words) else i + 1
            if _motion_verb(words[j]):
                words[j] = _third_person(words[j])
    return " ".join(words)


def _is_action(text: str) -> bool:
    return any(_motion_verb(w) for w in text.split())


def _starts_clause(text: str) -> bool:
    """Whether `text` (after a comma or an "and") starts a new action: a subject, or a motion verb
    that is not a gerund ("walks forward, swinging the arms" is one motion)."""
    text = _FILLER.sub("", text.strip().lower())
    first = text.split(" ", 1)[0]
    if _known_subject(text):
        return True
    return bool(first) and not first.endswith("ing") and _motion_verb(first) is not None


def _list_items(text: str) -> list[str]:
    """A list of verb phrases as its items: "walk forward, turn around and walk back" -> three; a
    phrase after a comma that does not start an action stays ("walks, arms raised"). A lone "A and
    B" stays whole unless B has its own subject."""
    items = []
    for piece in text.split(","):
        if items and not _starts_clause(piece):
            items[-1] += "," + piece
        else:
            items.append(piece)
    joined = re.compile(r"\s+and\s+(?=(?:he|she|they)\b)" if len(items) == 1 else r"\s+and\s+")
    return [part for item in items for part in _split_at_clauses(joined, item)]


def _split_at_clauses(pattern: re.Pattern, text: str) -> list[str]:
    """`text` split at the matches of `pattern` that a new action follows."""
    parts, begin = [], 0
    for m in pattern.finditer(text):
        if _starts_clause(text[m.end() :]):
            parts.append(text[begin : m.start()])
            begin = m.end()
    return [*parts, text[begin:]]


def _in_order(text: str) -> list[str]:
    """The clauses of a fragment in the order they happen: "after/once/when X, Y" and "Y after X" give
    [X, Y], "before X, Y" gives [Y, X]; an X without an action ("after a while") is dropped."""
    text = text.strip(" ,")
    for pattern in _LEADING_CLAUSE:
        m = pattern.match(text)
        if m:
            word, first, rest = m.group(1).lower(), m.group(2), m.group(3)
            first_part = _in_order(first) if _is_action(first) else []
            return [*_in_order(rest), *first_part] if word == "before" else [*first_part, *_in_order(rest)]
    for m in re.finditer(r",?\s+after\s+", text, re.IGNORECASE):
        later, earlier = text[: m.start()], text[m.end() :]
        if later.strip() and _is_action(earlier):
            return [*_in_order(earlier), *_in_order(later)]
    return _list_items(text)


def _fragments(paragraph: str) -> list[str]:
    """The paragraph's clauses in the order their actions happen, not yet cleaned."""

    def clauses(text: str) -> list[str]:
        return [c for piece in _SPLIT.split(text.strip()) if piece.strip(" ,") for c in _in_order(piece)]

    blocks: list[list[str]] = []
    for sentence in re.split(r"[.!?;]+", paragraph):
        first, *later = _BEFORE_THAT.split(sentence.strip())
        back = not first.strip() and bool(later)  # "Before that, ...": before the sentence ahead
        if back:
            first, *later = later
        for part in later:  # "A, before that B" -> B, then A
            first = f"{part}, then {first}"
        if back and blocks:
            blocks.insert(len(blocks) - 1, clauses(first))
        else:
            blocks.append(clauses(first))
    return [c for block in blocks for c in block]


def _clean(fragment: str) -> str:
    text = re.sub(r"\s+", " ", fragment).strip().lower()
    return _TRAILING.sub("", _FILLER.sub("", text).rstrip(" ,")).strip(" ,")


def _known_subject(text: str) -> str | None:
    return next((s for s in _SUBJECTS if text == s or text.startswith(s + " ")), None)


def _subject_of(text: str) -> str | None:
    """The subject `text` starts with: a known one, or the words before a verb in the third person
    ("a figure walks", "person kicks"); None when it starts with its verb."""
    known = _known_subject(text)
    if known:
        return known
    m = re.match(r"((?:(?:a|an|the)\s+)?([a-z]+))\s+([a-z]+)\b", text)
    if not m:
        return None
    noun, verb = m.group(2), m.group(3)
    is_verb = verb in ("is", "was") or (verb.endswith("s") and _motion_verb(verb) is not None)
    describes = noun.endswith("ly") or noun in _DIRECTIONS | _POSSESSIVES | _COUNTS or _motion_verb(noun)
    return m.group(1) if is_verb and not describes else None


def split_paragraph(paragraph: str, default_subject: str = "a person") -> list[str]:
    """Short prompts, in the order the actions happen, from a paragraph (ValueError when nothing is
    left)."""
    fragments = [t for t in map(_clean, _fragments(paragraph)) if t]
    subjects = [_subject_of(t) for t in fragments]
    subject = next((s for s in subjects if s and s not in _PRONOUNS), default_subject)
    prompts = []
    last_verb = "moves"  # for a fragment that only gives a direction
    for text, found in zip(fragments, subjects):
        if found:
            rest = text[len(found) :].strip()
            words = _FILLER.sub("", rest).split()
            if not words:
                continue
            if found in _PRONOUNS:
                text = f"{subject} {_predicate(words)}"
            elif words != rest.split():  # "the man starts by walking" -> "the man walks"
                text = f"{found} {_predicate(words)}"
        elif text.split(" ")[0] in _DIRECTIONS | _POSSESSIVES or text.startswith(_SIDES):
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
