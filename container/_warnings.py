"""The warnings a load caused, handed back to whoever asked for it.

A load that succeeds can still be wrong: ``rat: 5.0`` for ``rate`` loads
and runs on the default. The container logs such warnings, but the person
who typed the load reads a terminal, not the container's log, so each load
keeps its own (:attr:`~container._container.LoadedNode.warnings`) and the
answer carries them.

``composition_interfaces/LoadNode`` has no field for them. On success
rclcpp leaves ``error_message`` empty, and no client reads it then
(ros2cli's ``ros2 component load`` and launch_ros look at it only when
``success`` is false), so a successful answer carries them there: one line
per warning, as the container's log shows it without the time,
``[WARN] [talker]: Unknown parameter 'rat' ignored: ...``. A person or a
script reading the raw answer understands it as it is; ``container load``
parses it back (:func:`decode`) and logs each one again on its side.
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from dataclasses import dataclass

from ._text import MESSAGE_LIMIT, clip

__all__ = ["LoadWarning", "decode", "encode"]

#: One line of :func:`encode`: the logger's name, then the message.
_LINE = re.compile(r"^\[WARN\] \[([^\]\s]*)\]: (.+)$")


@dataclass(frozen=True, slots=True)
class LoadWarning:
    """One warning a load caused: the logger that logged it (the node's or the container's) and its message."""

    logger: str
    message: str

    def __str__(self) -> str:
        return f"[WARN] [{self.logger}]: {self.message}"


def encode(warnings: Iterable[LoadWarning]) -> str:
    """The warnings as a successful LoadNode answer's ``error_message``: one line each, at most 800 characters.

    Each line is one line whatever a peer sent: the messages echo its
    values through :func:`~container.clip`, and any line break left is
    folded here so that a line can never pass for another warning.
    """
    lines = [f"[WARN] [{warning.logger}]: {' '.join(warning.message.split())}" for warning in warnings]
    return clip("\n".join(lines), limit=MESSAGE_LIMIT)


def decode(text: str, *, default_logger: str) -> list[LoadWarning]:
    """The warnings in a successful answer's ``error_message``.

    :param default_logger: whose a line not in :func:`encode`'s form is
        (a container that writes something else there on success).
    """
    found = []
    for line in text.splitlines():
        if not line.strip():
            continue
        match = _LINE.match(line)
        if match:
            found.append(LoadWarning(match.group(1), match.group(2)))
        else:
            found.append(LoadWarning(default_logger, line.strip()))
    return found
