"""``container lifecycle nodes|get|set|list``: the ``ros2 lifecycle`` verbs."""

from __future__ import annotations

import argparse

__all__ = ["add_parser"]


def add_parser(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Register the lifecycle verbs (being written; see issue 4)."""
