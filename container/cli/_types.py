"""Argument types shared by the ``container`` sub-commands."""

from __future__ import annotations

import argparse

__all__ = ["name_value"]


def name_value(text: str) -> tuple[str, str]:
    """``name:=value``, the form of ``ros2``'s ``-p`` and ``-e`` arguments."""
    name, sep, value = text.partition(":=")
    if not sep or not name:
        raise argparse.ArgumentTypeError(f"expected 'name:=value', not {text!r}")
    return name, value
