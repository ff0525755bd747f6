"""The rclpy class :class:`~container.LifecycleNode` builds on, and how type checkers see it.

At run time this is rclpy's own :class:`rclpy.lifecycle.LifecycleNode`.
Type checkers read ``_base.pyi`` instead: rclpy 9 annotates the transition
callbacks (``on_configure`` ...) as returning a ``TransitionCallbackReturn``,
and mypy checks an override against every class in the MRO, so the ``async
def on_configure`` this container runs would be an "incompatible override"
in every plugin, whatever our own class declares. The stub declares rclpy's
lifecycle API with transition callbacks that may also be coroutines.
"""

from __future__ import annotations

import rclpy.lifecycle

__all__ = ["LifecycleNodeBase"]

LifecycleNodeBase = rclpy.lifecycle.LifecycleNode
