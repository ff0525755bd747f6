"""Driving a hosted lifecycle node through its transitions from the container.

The container brings nodes up (``autostart``) and down (unload, shutdown)
itself rather than through the nodes' ``change_state`` services: in-process,
without DDS, and inside the node's own callback group so a transition never
overlaps the node's callbacks or a ``change_state`` request from outside.
"""

from __future__ import annotations

import asyncio
import inspect
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from rclpy.lifecycle import LifecycleNodeMixin, TransitionCallbackReturn

from .._compat import state_machine
from .._errors import TransitionError
from ._node import LifecycleNode

if TYPE_CHECKING:
    from rclpy.node import Node

    from ..executor import AsyncioExecutor

__all__ = ["bring_down", "bring_up", "is_lifecycle", "state_of", "transition"]

#: The transitions a node takes down from each primary state, towards finalized.
_DOWN = {"active": "deactivate", "inactive": "cleanup", "unconfigured": "shutdown"}
_UP = {"unconfigured": "configure", "inactive": "activate"}
_UP_TO = ("inactive", "active")

#: How long past its own timeout a node of our base may take to fail back.
_FAIL_BACK_MARGIN_S = 1.0


def is_lifecycle(node: Node) -> bool:
    """Whether ``node`` has lifecycle states (ours or any rclpy lifecycle node): the container drives it."""
    return isinstance(node, LifecycleNodeMixin)


def state_of(node: Node) -> str:
    """The label of the node's current state (``active``, ``configuring``, ...)."""
    # rclpy keeps no public accessor for the state in Jazzy; holding the
    # machine keeps it from being freed meanwhile (InvalidHandle once it is).
    machine = state_machine(node)
    with machine:
        _, label = machine.current_state
    return str(label)


def _trigger(node: Node, label: str, timeout: float) -> Callable[[], Any]:
    if isinstance(node, LifecycleNode):
        # The node bounds its own callbacks, so a slow one fails back to its
        # start state instead of being abandoned mid-transition.
        async def run_bounded() -> bool:
            return await node.transition(label, timeout=timeout)

        return run_bounded
    custom = getattr(node, "transition", None)
    if custom is not None and inspect.iscoroutinefunction(custom):
        # Any other node that drives its own (possibly async) transitions.
        async def run_custom() -> bool:
            return bool(await custom(label))

        return run_custom
    trigger = getattr(node, f"trigger_{label}")

    def run() -> bool:
        return bool(trigger() == TransitionCallbackReturn.SUCCESS)

    return run


async def transition(
    executor: AsyncioExecutor, node: Node, label: str, *, timeout: float
) -> None:
    """Run one transition in the node's default callback group.

    :raises TransitionError: the transition failed, raised, or timed out.
    """
    name = node.get_fully_qualified_name()
    # Our node base times itself out; the margin lets its failure arrive first.
    limit = timeout + _FAIL_BACK_MARGIN_S if isinstance(node, LifecycleNode) else timeout
    try:
        ok = await asyncio.wait_for(
            executor.run_in_group(
                node.default_callback_group, _trigger(node, label, timeout), node=node
            ),
            limit,
        )
    except TimeoutError:
        raise TransitionError(f"no answer within {timeout:g} s", node=name, transition=label) from None
    except (KeyboardInterrupt, asyncio.CancelledError):
        raise
    except BaseException as exc:
        raise TransitionError(f"{type(exc).__name__}: {exc}", node=name, transition=label) from exc
    if not ok:
        reason = node.last_failure if isinstance(node, LifecycleNode) else None
        because = f": {reason}" if reason else ""
        raise TransitionError(
            f"failed{because}; the node is now {state_of(node)}", node=name, transition=label
        )


async def bring_up(
    executor: AsyncioExecutor, node: Node, *, timeout: float, until: str = "active"
) -> None:
    """Configure and activate, from wherever the node stands.

    :param until: ``inactive`` stops after configuring (the first of the
        two phases of a Nav2-style bring-up); ``active`` goes all the way.
    """
    if until not in _UP_TO:
        raise ValueError(f"until must be one of {', '.join(_UP_TO)}, not {until!r}")
    while (state := state_of(node)) != until and (label := _UP.get(state)) is not None:
        await transition(executor, node, label, timeout=timeout)


async def bring_down(executor: AsyncioExecutor, node: Node, *, timeout: float) -> str:
    """Deactivate, clean up and shut down, as the node's state needs.

    :return: the state the node ended in (``finalized`` unless a step failed).
    :raises TransitionError: a step failed; the node is left where it stopped.
    """
    while (label := _DOWN.get(state_of(node))) is not None:
        await transition(executor, node, label, timeout=timeout)
    return state_of(node)
