"""Calling a lifecycle node's standard services from asyncio code.

The lifecycle manager and ``container lifecycle`` drive nodes they may not
host (another process, a C++ node), so both go through the services every
lifecycle node serves. Everything here runs on the executor's event loop;
rclpy futures are awaited through the executor's bridge
(:func:`container.executor.result`), never directly, which would busy-wait
outside the executor's own callbacks.
"""

from __future__ import annotations

import asyncio
import time
from typing import TYPE_CHECKING, Any

from lifecycle_msgs.msg import Transition, TransitionDescription
from lifecycle_msgs.srv import ChangeState, GetAvailableTransitions, GetState

from .._errors import TransitionError
from ..executor import result as future_result

if TYPE_CHECKING:
    from rclpy.callback_groups import CallbackGroup
    from rclpy.client import Client
    from rclpy.node import Node

__all__ = ["LifecycleClient", "transition_id"]

_READY_POLL_S = 0.02
#: How long a query waits for its answer before asking again.
_RESEND_S = 1.0

#: Transition ids by label; ``shutdown`` depends on the state it leaves.
_IDS: dict[str, int] = {
    "configure": Transition.TRANSITION_CONFIGURE,
    "cleanup": Transition.TRANSITION_CLEANUP,
    "activate": Transition.TRANSITION_ACTIVATE,
    "deactivate": Transition.TRANSITION_DEACTIVATE,
}
_SHUTDOWN_IDS: dict[str, int] = {
    "unconfigured": Transition.TRANSITION_UNCONFIGURED_SHUTDOWN,
    "inactive": Transition.TRANSITION_INACTIVE_SHUTDOWN,
    "active": Transition.TRANSITION_ACTIVE_SHUTDOWN,
}


def transition_id(label: str, state: str) -> int:
    """The id of transition ``label`` taken from primary state ``state``."""
    if label == "shutdown":
        return _SHUTDOWN_IDS[state]
    return _IDS[label]


class LifecycleClient:
    """The ``change_state``, ``get_state`` and ``get_available_transitions`` of one node.

    :param target: the node's full name.
    :param service_timeout: seconds to wait for a service to appear and for
        ``get_state``/``get_available_transitions`` to answer.
    """

    def __init__(
        self,
        node: Node,
        target: str,
        *,
        callback_group: CallbackGroup | None = None,
        service_timeout: float = 5.0,
    ) -> None:
        self.node = node
        self.target = target
        self.service_timeout = service_timeout
        base = target.rstrip("/")
        self._change: Client[Any, Any] = node.create_client(
            ChangeState, f"{base}/change_state", callback_group=callback_group
        )
        self._get: Client[Any, Any] = node.create_client(
            GetState, f"{base}/get_state", callback_group=callback_group
        )
        self._transitions: Client[Any, Any] = node.create_client(
            GetAvailableTransitions,
            f"{base}/get_available_transitions",
            callback_group=callback_group,
        )
        self._graph: Client[Any, Any] = node.create_client(
            GetAvailableTransitions, f"{base}/get_transition_graph", callback_group=callback_group
        )

    def ready_now(self) -> bool:
        return bool(self._change.service_is_ready() and self._get.service_is_ready())

    async def wait_ready(self, *, timeout: float | None = None) -> bool:
        """Wait for the node's ``change_state`` and ``get_state`` services."""
        deadline = time.monotonic() + (self.service_timeout if timeout is None else timeout)
        while not self.ready_now():
            if time.monotonic() >= deadline:
                return False
            await asyncio.sleep(_READY_POLL_S)
        return True

    async def _call(
        self,
        client: Client[Any, Any],
        request: Any,
        *,
        what: str,
        timeout: float | None,
        resend: bool = False,
    ) -> Any:
        """Call a service once it is discovered.

        :param resend: repeat the request every :data:`_RESEND_S` until an
            answer comes; for queries only. A service is "ready" once the
            request side has matched; an answer sent before the reply side
            has matched too is lost (Fast DDS), so a query that seems to hang
            just after discovery is asked again.
        """
        deadline = time.monotonic() + self.service_timeout
        while not client.service_is_ready():
            if time.monotonic() >= deadline:
                raise TransitionError(
                    f"service {client.srv_name} not available within {self.service_timeout:g} s",
                    node=self.target,
                    transition=what,
                )
            await asyncio.sleep(_READY_POLL_S)
        give_up = None if timeout is None else time.monotonic() + timeout
        while True:
            wait = None if give_up is None else max(0.0, give_up - time.monotonic())
            if resend:
                wait = _RESEND_S if wait is None else min(wait, _RESEND_S)
            future = client.call_async(request)
            try:
                return await future_result(future, timeout=wait)
            except TimeoutError:
                client.remove_pending_request(future)
                if give_up is not None and time.monotonic() >= give_up:
                    raise TransitionError(
                        f"{client.srv_name} did not answer within {timeout} s",
                        node=self.target,
                        transition=what,
                    ) from None

    async def get_state(self) -> tuple[int, str]:
        """``(id, label)`` of the node's current state."""
        response = await self._call(
            self._get,
            GetState.Request(),
            what="get_state",
            timeout=self.service_timeout,
            resend=True,
        )
        return int(response.current_state.id), str(response.current_state.label)

    async def change_state(self, transition: Transition, *, timeout: float | None) -> bool:
        """Request a transition; ``success`` of the answer (``timeout`` ``None``: wait)."""
        label = transition.label or str(transition.id)
        response = await self._call(
            self._change, ChangeState.Request(transition=transition), what=label, timeout=timeout
        )
        return bool(response.success)

    async def available_transitions(self, *, graph: bool = False) -> list[TransitionDescription]:
        """The transitions available now, or the whole graph."""
        client = self._graph if graph else self._transitions
        response = await self._call(
            client,
            GetAvailableTransitions.Request(),
            what="get_available_transitions",
            timeout=self.service_timeout,
            resend=True,
        )
        return list(response.available_transitions)

    def close(self) -> None:
        for client in (self._change, self._get, self._transitions, self._graph):
            self.node.destroy_client(client)
