"""Text from the outside, made fit for a log line or a service's answer.

Anything a peer sends (a package name, a remap rule, a parameter's value, a
port to open, a transition label) may be a megabyte long: echoed verbatim it
floods the log, the terminal and the answer (a 1 MB ``comm.serial_port`` made
a 1,000,119-character ERROR line). Every such value is echoed through
:func:`clip`, which keeps its start and says how long it was, so the reader
still sees what was sent and that it was cut.
"""

from __future__ import annotations

__all__ = ["CLIP_LIMIT", "MESSAGE_LIMIT", "clip"]

#: Characters of one value from outside kept in a log line or an answer:
#: longer than any device path, node name or parameter a person types
#: (rcl bounds names at 255 characters, but it checks them after we echo
#: them), short enough that a line holding a few such values fits a screen.
CLIP_LIMIT = 200

#: Characters of a whole message built around such values (its words and a
#: few clipped values); the bound of a log line or an answer that holds a
#: foreign error's text, which may echo a value nobody clipped.
MESSAGE_LIMIT = 4 * CLIP_LIMIT


def clip(value: object, *, limit: int = CLIP_LIMIT, quote: bool = False) -> str:
    """``value`` itself if short, else its first ``limit`` characters, ``…`` and its length.

    ``clip("/dev/" + "a" * 1048571, quote=True)`` is
    ``'/dev/aaaa…' (1048576 characters)``, with 200 characters kept.

    :param value: text (a message, a name); anything else is shown as its ``str``.
    :param quote: show it as Python writes it (``repr``): a string as a
        literal, quotes and escapes included, so that its newline or terminal
        escape sequence can neither forge a log line nor drive the operator's
        terminal; a string's length is then its own, not its literal's.
    """
    if quote and not isinstance(value, str):
        return clip(repr(value), limit=limit)
    text = value if isinstance(value, str) else str(value)
    if len(text) <= limit:
        return repr(text) if quote else text
    kept = text[:limit]
    if quote:
        literal = repr(kept)
        return f"{literal[:-1]}…{literal[-1]} ({len(text)} characters)"
    return f"{kept}… ({len(text)} characters)"
