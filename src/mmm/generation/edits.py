"""What an edit request may ask for, checked in one place: the command line (`mmm edit`) and the
served part-aware bundle build an `EditRequest` and get the same rules and the same refusals.

    inbetween   keep a start and an end of the source (two or more --keep ranges), generate between
    outpaint    keep one range of the source, generate around it (--length, --place)
    complete    keep the start of the source (a range from frame 0), generate the rest
    upper-body  keep the source's lower body, generate a new upper body from the text; --lower-mask
                (a share of the lower-body codes hidden, default 0.5) or --lower-keep (frame ranges
                whose lower-body codes are shown) say how much of it constrains the upper body

Messages name each value the caller's way: `names` maps a field (text, keep, lower_mask,
lower_keep, place, length) to how the caller spells it (the CLI: --text, --keep, ...); a field
not named there is spelt as itself (a request row's column names).

This module imports nothing heavy: the CLI reads `EDIT_KINDS` while it builds its parser.
"""

from __future__ import annotations

from dataclasses import dataclass

EDIT_KINDS = ("inbetween", "outpaint", "complete", "upper-body")
UPPER_BODY = "upper-body"

Ranges = tuple[tuple[int, int], ...]


class EditRequestError(ValueError):
    """An edit request that breaks a rule; `field` is the value at fault (text, keep, lower_mask, ...)."""

    def __init__(self, field: str, message: str):
        self.field = field
        super().__init__(message)


def parse_ranges(text: str, name: str = "keep", field: str = "keep") -> Ranges:
    """Frame ranges from 'START:END[,START:END]'; EditRequestError naming the option `name` otherwise."""
    ranges = []
    for part in text.split(","):
        try:
            a, b = (int(x) for x in part.split(":"))
        except ValueError:
            raise EditRequestError(
                field, f"{name} {text!r}: write frame ranges as START:END[,START:END], e.g. 0:40,150:196"
            ) from None
        ranges.append((a, b))
    return tuple(ranges)


def sampling_defaults(kind: str | None) -> dict:
    """SamplingConfig fields whose default differs for an edit of `kind` (None: plain generation):
    upper-body edits sample with classifier-free guidance."""
    if kind != UPPER_BODY:
        return {}
    # imported here: upper_body imports torch, and the CLI's parser reads this module
    from mmm.generation.upper_body import UPPER_BODY_GUIDANCE

    return {"guidance_scale": UPPER_BODY_GUIDANCE}


@dataclass(frozen=True)
class EditRequest:
    """A checked edit: build one with `EditRequest.parse`, run it with `run`.

    keep: the source frames kept (whole-body kinds). lower_mask/lower_keep (upper-body): one of the
    two, the other None; lower_mask is the default share when neither was given. length/place
    (whole-body kinds): output frames (None: the source's) and the output frame where the source
    starts; the model checks them against the source and its limits."""

    kind: str
    text: str | None = None
    keep: Ranges | None = None
    lower_mask: float | None = None
    lower_keep: Ranges | None = None
    length: int | None = None
    place: int = 0

    @classmethod
    def parse(
        cls,
        kind: str,
        text: str | None = None,
        keep: str | Ranges | None = None,
        lower_mask: float | None = None,
        lower_keep: str | Ranges | None = None,
        length: int | None = None,
        place: int = 0,
        names: dict[str, str] | None = None,
    ) -> EditRequest:
        """The request, or EditRequestError (a ValueError) saying which rule it breaks.
        keep/lower_keep: ranges, or text as 'START:END[,START:END]'."""
        n = {k: k for k in ("text", "keep", "lower_mask", "lower_keep", "place", "length")} | (names or {})
        if kind not in EDIT_KINDS:
            raise EditRequestError("kind", f"edit kind {kind!r} is not one of {', '.join(EDIT_KINDS)}")
        if place < 0:
            raise EditRequestError(
                "place",
                f"{n['place']} {place} is not allowed: the output frame where "
                "the source starts, 0 or more (a multiple of 4)",
            )
        if kind == UPPER_BODY:
            from mmm.generation.upper_body import DEFAULT_LOWER_MASK  # see sampling_defaults

            if keep:
                raise EditRequestError(
                    "keep",
                    "upper-body keeps the whole lower body of the source; choose "
                    "how much of it constrains the upper body with "
                    f"{n['lower_mask']} SHARE or {n['lower_keep']} A:B",
                )
            if not text:
                raise EditRequestError(
                    "text",
                    f"upper-body needs {n['text']} saying what the upper body "
                    f"does, e.g. {n['text']} 'a man punches with both hands'",
                )
            if lower_mask is not None and lower_keep is not None:
                raise EditRequestError(
                    "lower_mask",
                    f"give {n['lower_mask']} (a share of lower-body codes "
                    f"hidden) or {n['lower_keep']} (frame ranges shown), not both",
                )
            if lower_mask is not None and not 0.0 <= lower_mask <= 1.0:
                raise EditRequestError(
                    "lower_mask",
                    f"{n['lower_mask']} {lower_mask}: a share between 0 "
                    "(the lower body constrains fully) and 1 (only the text)",
                )
            if isinstance(lower_keep, str):
                lower_keep = parse_ranges(lower_keep, n["lower_keep"], "lower_keep")
            if lower_keep is None and lower_mask is None:
                lower_mask = DEFAULT_LOWER_MASK
            keep = None
        else:
            if lower_mask is not None or lower_keep is not None:
                raise EditRequestError(
                    "lower_mask",
                    f"{n['lower_mask']}/{n['lower_keep']} are for `mmm edit upper-body`, not {kind}",
                )
            if not keep:
                raise EditRequestError(
                    "keep", f"{kind} needs {n['keep']} START:END[,START:END] (source frames to keep)"
                )
            keep = parse_ranges(keep, n["keep"]) if isinstance(keep, str) else keep
            ordered = sorted(keep, key=lambda r: r[0])
            for (a, b), (c, d) in zip(ordered, ordered[1:]):
                if c < b:
                    raise EditRequestError(
                        "keep",
                        f"{n['keep']} ranges {a}:{b} and {c}:{d} overlap: give each kept frame once, e.g. "
                        "0:40,150:196",
                    )
        if text is not None and not text.strip():
            raise EditRequestError(
                "text",
                f"{n['text']} is empty: describe the motion, e.g. {n['text']} 'a person walks forward'",
            )
        if kind == "inbetween" and len(keep) < 2:
            raise EditRequestError(
                "keep", f"inbetween keeps a start and an end of the source: {n['keep']} 0:40,150:196 (frames)"
            )
        if kind == "outpaint" and len(keep) != 1:
            raise EditRequestError(
                "keep",
                "outpaint keeps one middle range and generates around it: "
                f"{n['keep']} 60:140 [{n['length']} N {n['place']} P]",
            )
        if kind == "complete" and keep[0][0] != 0:
            raise EditRequestError(
                "keep",
                "complete keeps the start of the source and generates the rest: "
                f"{n['keep']} 0:80 [{n['length']} N]",
            )
        return cls(
            kind,
            text,
            None if keep is None else tuple(map(tuple, keep)),
            lower_mask,
            None if lower_keep is None else tuple(map(tuple, lower_keep)),
            length,
            place,
        )

    def run(self, model, source, sampling=None, seed: int | None = None, num_samples: int = 1):
        """The edit of `source` (un-normalized features (T, D)) by a TextToMotion model: its Generated."""
        if self.kind == UPPER_BODY:
            lower_keep = None if self.lower_keep is None else list(self.lower_keep)
            return model.edit_upper_body(
                source, self.text, self.lower_mask, lower_keep, sampling, seed, num_samples
            )
        return model.edit(
            source, list(self.keep), self.text, self.length, self.place, sampling, seed, num_samples
        )
