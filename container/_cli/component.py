"""``container load|unload|list|types``: the ``ros2 component`` verbs."""

from __future__ import annotations

import argparse

__all__ = ["add_parser"]


def add_parser(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Register the component verbs (being written; see issue 3)."""
