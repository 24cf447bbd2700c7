"""Commands the harness sends the CNN target over the transport (a COMMAND message,
``PROTOCOL.md`` section 4.7), and the target's replies. Plain text, one line:

=========================  ===================================================
``swap detector cnn|cv``   use the CNN detector or the OpenCV baseline's from the
                           next frame on
``swap steering cnn|cv``   use the steering CNN or the baseline's lane keeping
``status``                 the active models, counters and inference times
=========================  ===================================================

A reply starts with ``ok`` or ``error:``; a swap's reply names the models now
active and the last frame processed before the swap, so the run's record shows
exactly which frames each model answered.
"""

from __future__ import annotations

from dataclasses import dataclass

SLOTS = ("detector", "steering")
MODELS = ("cnn", "cv")
USAGE = "commands: 'swap detector cnn|cv', 'swap steering cnn|cv', 'status'"


class CommandError(ValueError):
    """A command that cannot be parsed; the message says what is valid."""


@dataclass(frozen=True)
class Swap:
    slot: str
    model: str


@dataclass(frozen=True)
class Status:
    pass


def parse(text: str) -> Swap | Status:
    """The command in ``text`` (case and surrounding blanks ignored).

    Raises:
        CommandError: unknown command, slot or model (the message lists the valid ones).
    """
    words = text.strip().lower().split()
    if words == ["status"]:
        return Status()
    if len(words) == 3 and words[0] == "swap":
        slot, model = words[1], words[2]
        if slot not in SLOTS:
            raise CommandError(f"unknown slot {slot!r}; valid: {', '.join(SLOTS)}")
        if model not in MODELS:
            raise CommandError(f"unknown model {model!r} for the {slot}; valid: {', '.join(MODELS)}")
        return Swap(slot, model)
    raise CommandError(f"unknown command {text.strip()[:60]!r}; {USAGE}")
