"""Message info as rclpy's own executors hand it to ``(message, info)`` callbacks.

rclpy 9 (Kilted) added the publisher's gid to the dictionary
(``rclpy.subscription.MessageInfo``); rclpy 7 (Jazzy) has none. The
executor's compiled take and intra-process delivery give exactly the keys
the running rclpy gives, so a callback reading ``info["publisher_gid"]``
works in the container where it works under rclpy's executors, and only there.
"""

from __future__ import annotations

from typing import Any

import rclpy.subscription

from ._engine import publisher_gid as _publisher_gid

__all__ = ["HAS_PUBLISHER_GID", "publisher_gid"]

#: Whether this rclpy's message info carries ``publisher_gid`` (rclpy 9 and later).
HAS_PUBLISHER_GID: bool = "publisher_gid" in getattr(
    getattr(rclpy.subscription, "MessageInfo", None), "__annotations__", {}
)


def publisher_gid(publisher: Any) -> dict[str, Any] | None:
    """``publisher``'s gid as message info names it, or ``None`` where this rclpy's has none."""
    if not HAS_PUBLISHER_GID:
        return None
    return _publisher_gid(publisher.handle)
