"""Fault containment: an exception escaping an active node's callback fails that node.

rclpy leaves a node whose callback raised exactly where it was: active, and
perhaps half broken. Here the executor's ``on_callback_error`` hook
(:func:`contain_fault`) sends such a node through error processing
(``on_error``: success -> unconfigured, failure -> finalized), each step on
``transition_event``, while every other node keeps running. The executor has
already logged the exception with its traceback when the hook runs.

Error processing runs in the node's default callback group, like any other
transition, so it never overlaps the node's own callbacks or a
``change_state`` request.
"""

from __future__ import annotations

import asyncio
import weakref
from typing import TYPE_CHECKING

from lifecycle_msgs.msg import Transition
from rclpy.lifecycle import (
    LifecycleNodeMixin,
    LifecyclePublisher,
    LifecycleState,
    TransitionCallbackReturn,
)

from .._compat import managed_entities, state_machine
from ..executor import AsyncioExecutor, describe
from ._node import LifecycleNode
from ._transitions import state_of

if TYPE_CHECKING:
    from rclpy.node import Node

__all__ = ["contain_fault", "process_error"]

#: Nodes with error processing queued or running: a timer raising at 100 Hz
#: must not queue a hundred of them.
_pending: weakref.WeakSet[Node] = weakref.WeakSet()


def contain_fault(node: Node, entity: object, error: BaseException) -> None:
    """``on_callback_error`` hook of :class:`~container.AsyncioExecutor`.

    Safe from any thread. Nodes that are not lifecycle nodes, not active, or
    not on an :class:`AsyncioExecutor` are left alone (the error stays logged).
    """
    if not isinstance(node, LifecycleNodeMixin) or isinstance(error, asyncio.CancelledError):
        return
    executor = node.executor
    if not isinstance(executor, AsyncioExecutor) or state_of(node) != "active":
        return
    if node in _pending:
        return
    _pending.add(node)
    node.get_logger().error(
        f"Fault in active node: {describe(entity)} raised {type(error).__name__}: {error}"
    )
    # create_task is the executor's thread-safe way onto its loop.
    executor.create_task(_contain(executor, node, error))


async def _contain(executor: AsyncioExecutor, node: Node, error: BaseException) -> None:
    try:
        if isinstance(node, LifecycleNode):

            async def fail() -> str:
                return await node.fail(error)

            await executor.run_in_group(node.default_callback_group, fail, node=node)
        else:
            await executor.run_in_group(
                node.default_callback_group, lambda: process_error(node), node=node
            )
    except Exception as exc:  # nobody awaits this task: say what went wrong
        node.get_logger().error(f"Error processing failed: {type(exc).__name__}: {exc}")
    finally:
        _pending.discard(node)


def process_error(node: Node) -> str:
    """Error processing for a plain rclpy lifecycle node that is active.

    The same route as :meth:`LifecycleNode.fail`, for nodes not built on the
    project's base: synchronous ``on_error``, rcl state machine driven directly
    so that ``transition_event`` shows every step.

    :return: the state the node ends in.
    """
    if state_of(node) != "active":
        return state_of(node)
    machine = state_machine(node)
    node.get_logger().error("Entering error processing")
    machine.trigger_transition_by_id(Transition.TRANSITION_DEACTIVATE, True)
    machine.trigger_transition_by_label(TransitionCallbackReturn.ERROR.to_label(), True)
    try:
        outcome = node.on_error(LifecycleState(label="active", state_id=3))  # type: ignore[attr-defined]
    except KeyboardInterrupt:
        raise
    except BaseException as exc:
        node.get_logger().error(f"on_error() raised {type(exc).__name__}: {exc}")
        outcome = TransitionCallbackReturn.ERROR
    if not isinstance(outcome, TransitionCallbackReturn):
        outcome = TransitionCallbackReturn.ERROR
    machine.trigger_transition_by_label(outcome.to_label(), True)
    # rclpy's on_error leaves lifecycle publishers enabled; they must not publish.
    for entity in list(managed_entities(node)):
        if isinstance(entity, LifecyclePublisher):
            entity.on_deactivate(LifecycleState(label=state_of(node), state_id=0))
    final = state_of(node)
    node.get_logger().info(f"Error processing done: the node is {final}")
    return final
