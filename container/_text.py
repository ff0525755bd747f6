"""Text from the outside, made fit for a log line.

Anything a peer sends (a package name, a remap rule, a transition label) may
be a megabyte long; logged verbatim it floods the log and the terminal.
"""

from __future__ import annotations

__all__ = ["clip"]

#: Characters of a request string kept in a log line or an error message.
CLIP_LIMIT = 200


def clip(text: str, *, limit: int = CLIP_LIMIT) -> str:
    """``text`` itself if short, else its start and its length."""
    if len(text) <= limit:
        return text
    return f"{text[:limit]}... ({len(text)} characters)"
