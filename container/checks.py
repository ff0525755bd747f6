"""Checks for configuration values: one set for the container, its manager and plugins.

A value from a container file, a manager setting or a node parameter is
checked by the same functions, so the same mistake reads the same wherever
it is made. Each returns the value converted to the type it promises, or
raises :class:`~container.ConfigError` whose ``source`` says where the value
came from (``where``) and whose ``reason`` says what is wrong with it (the
value echoed clipped, :func:`~container.clip`)::

    timeout = checks.number(value, where="comm.timeout_msec", positive=True)
"""

from __future__ import annotations

import difflib
import math
from collections.abc import Iterable, Sequence
from typing import Any, Protocol

from ._errors import ConfigError
from ._text import clip

__all__ = ["boolean", "integer", "number", "string", "strings", "unread_parameters"]


def string(value: Any, *, where: str, empty: bool = False) -> str:
    """A string; blank ones are refused unless ``empty``."""
    if not isinstance(value, str) or not (empty or value.strip()):
        kind = "a string" if empty else "a non-empty string"
        raise ConfigError(f"must be {kind}, not {clip(value, quote=True)}", source=where)
    return value


def strings(value: Any, *, where: str) -> tuple[str, ...]:
    """A list of strings."""
    if not isinstance(value, Sequence) or isinstance(value, str) or not all(isinstance(v, str) for v in value):
        raise ConfigError(f"must be a list of strings, not {clip(value, quote=True)}", source=where)
    return tuple(value)


def boolean(value: Any, *, where: str) -> bool:
    """``true`` or ``false``; never a number or a string that looks like one."""
    if not isinstance(value, bool):
        raise ConfigError(f"must be true or false, not {clip(value, quote=True)}", source=where)
    return value


def integer(value: Any, *, where: str, minimum: int | None = None, maximum: int | None = None) -> int:
    """An integer (a float with an integral value counts), within the bounds given."""
    if isinstance(value, float) and value.is_integer():
        value = int(value)
    if isinstance(value, bool) or not isinstance(value, int):
        raise ConfigError(f"must be an integer, not {clip(value, quote=True)}", source=where)
    _bounds(value, minimum, maximum, where)
    return value


def number(
    value: Any,
    *,
    where: str,
    positive: bool = False,
    minimum: float | None = None,
    maximum: float | None = None,
) -> float:
    """A finite number (NaN and infinities are refused), within the bounds given.

    :param positive: refuse zero and below.
    """
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ConfigError(f"must be a finite number, not {clip(value, quote=True)}", source=where)
    if positive and value <= 0:
        raise ConfigError(f"must be positive, not {value:g}", source=where)
    _bounds(value, minimum, maximum, where)
    return float(value)


def _bounds(value: float, minimum: float | None, maximum: float | None, where: str) -> None:
    if minimum is not None and maximum is not None and not minimum <= value <= maximum:
        raise ConfigError(f"must be within [{minimum:g}, {maximum:g}], not {value:g}", source=where)
    if minimum is not None and value < minimum:
        raise ConfigError(f"must be >= {minimum:g}, not {value:g}", source=where)
    if maximum is not None and value > maximum:
        raise ConfigError(f"must be <= {maximum:g}, not {value:g}", source=where)


class _DeclaresParameters(Protocol):
    def has_parameter(self, name: str) -> bool: ...

    def get_parameters_by_prefix(self, prefix: str) -> dict[str, Any]: ...


#: Parameters rclpy declares on every node, whoever overrides them.
_ROS_PARAMETERS = frozenset({"use_sim_time", "start_type_description_service"})


def unread_parameters(node: _DeclaresParameters, names: Iterable[str], *, likely_typos: bool = False) -> list[str]:
    """A warning for each of ``names`` (parameter overrides given to ``node``) that no declared parameter takes.

    rclpy keeps an override nobody declares without a word, so ``rat: 5.0``
    for ``rate`` runs on the default. Call it once the node has declared
    what it reads (after its constructor; a lifecycle node after configure).
    Each warning offers the closest declared name, if one is close.

    :param likely_typos: only the names a declared one is close to. Before a
        lifecycle node's configure, a name nothing declares yet may still be
        declared by configure; one next to a declared name is a typo.
    """
    unread = [name for name in dict.fromkeys(names) if name not in _ROS_PARAMETERS and not node.has_parameter(name)]
    if not unread:
        return []
    declared = [name for name in node.get_parameters_by_prefix("") if name not in _ROS_PARAMETERS]
    warnings = []
    for name in unread:
        close = difflib.get_close_matches(name, declared, n=1)
        if likely_typos and not close:
            continue
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        warnings.append(f"Unknown parameter {clip(name, quote=True)} ignored: this node does not read it{hint}")
    return warnings
