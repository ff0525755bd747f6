"""Argument types shared by the ``container`` sub-commands."""

from __future__ import annotations

import argparse

__all__ = ["CLIENT_TIMEOUT_S", "name_value", "positive_seconds"]

#: How long a client command waits for a service, and for each answer
#: (``--timeout``): ros2cli waits without a limit; a script must not.
CLIENT_TIMEOUT_S = 10.0


def name_value(text: str) -> tuple[str, str]:
    """``name:=value``, the form of ``ros2``'s ``-p`` and ``-e`` arguments."""
    name, sep, value = text.partition(":=")
    if not sep or not name:
        raise argparse.ArgumentTypeError(f"expected 'name:=value', not {text!r}")
    return name, value


def positive_seconds(text: str) -> float:
    """A positive, finite number of seconds (``--timeout``)."""
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"expected a positive number of seconds, not {text!r}")
    return value
