"""Message info as rclpy's own executors hand it to ``(message, info)`` callbacks.

rclpy 9 (Kilted) added the publisher's gid to the dictionary
(``rclpy.subscription.MessageInfo``); rclpy 7 (Jazzy) has none. The
executor's compiled take and intra-process delivery give exactly the keys
the running rclpy gives, so a callback reading ``info["publisher_gid"]``
works in the container where it works under rclpy's executors, and only there.

A publisher's gid comes from its rcl handle on the compiled engine. rclpy
offers no accessor for it to Python, so on the Python engine it is found in
the ROS graph instead, given the publisher's node: the gid of that node's
one publisher on the topic (the graph knows a process's own publishers as
soon as they are made), the same gid rclpy's takes report.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import rclpy.subscription
from rclpy.utilities import get_rmw_implementation_identifier

from ._engine import publisher_gid as _publisher_gid

if TYPE_CHECKING:
    from rclpy.node import Node

__all__ = ["HAS_PUBLISHER_GID", "publisher_gid"]

#: Whether this rclpy's message info carries ``publisher_gid`` (rclpy 9 and later).
HAS_PUBLISHER_GID: bool = "publisher_gid" in getattr(
    getattr(rclpy.subscription, "MessageInfo", None), "__annotations__", {}
)


def publisher_gid(publisher: Any, *, node: Node | None = None) -> dict[str, Any] | None:
    """``publisher``'s gid as message info names it, or ``None`` where this rclpy's has none.

    :param node: the publisher's node, where the Python engine finds the gid
        (see the module); without it, or where that node has several
        publishers on the topic, the Python engine knows none (``None``).
    """
    if not HAS_PUBLISHER_GID:
        return None
    try:
        return _publisher_gid(publisher.handle)
    except NotImplementedError:
        return None if node is None else _gid_in_graph(node, publisher.topic_name)


def _gid_in_graph(node: Node, topic: str) -> dict[str, Any] | None:
    """The gid of ``node``'s one publisher on ``topic``, as the ROS graph names it."""
    name, namespace = node.get_name(), node.get_namespace()
    found = [
        info.endpoint_gid
        for info in node.get_publishers_info_by_topic(topic)
        if info.node_name == name and info.node_namespace == namespace
    ]
    if len(found) != 1:
        return None
    return {"implementation_identifier": get_rmw_implementation_identifier(), "data": bytes(found[0])}
