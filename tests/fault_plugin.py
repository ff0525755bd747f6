"""A plugin whose node misbehaves on request: the fault matrix's subject.

``tests_faults::Faulty`` (plain callbacks) and ``tests_faults::FaultyAsync``
(``async def`` ones) take two parameters: ``fault`` (what goes wrong) and
``where`` (in which callback, at its first call). Loaded into a container beside a healthy talker, it shows what a
careless or hostile plugin can do to its neighbours.
"""

from __future__ import annotations

import asyncio
import sys
import threading
import time
from typing import TYPE_CHECKING, Any

from rclpy.lifecycle import LifecycleState, TransitionCallbackReturn
from std_msgs.msg import String
from std_srvs.srv import Trigger

from container import LifecycleNode, RegisterNodeType, hookimpl

if TYPE_CHECKING:
    # Only in the typing facade (a .pyi): a plain result, or an awaitable of one.
    from container.lifecycle._base import TransitionOutcome

FAULTS = ("raise", "exit", "busy", "sleep", "await", "thread", "slow")
WHERES = (
    "constructor",
    "configure",
    "activate",
    "deactivate",
    "cleanup",
    "shutdown",
    "timer",
    "subscription",
    "service",
)
TRANSITIONS = ("configure", "activate", "deactivate", "cleanup", "shutdown")

#: How long "forever" lasts: longer than any test waits, short enough that
#: a thread left behind does not outlive the test run by much.
FOREVER_S = 120.0
#: How long the ``slow`` fault (not a fault: just slow) takes, then succeeds.
SLOW_S = 0.5


class FaultInjected(RuntimeError):
    """What the ``raise`` fault raises."""


def _misbehave_plainly(fault: str, where: str, forever: float = FOREVER_S) -> None:
    # Said before doing it, so a test knows the fault has struck.
    print(f"misbehaving: {fault} in {where}", flush=True)
    if fault == "raise":
        raise FaultInjected(f"fault in {where}")
    if fault == "exit":
        sys.exit(3)
    if fault == "busy":
        deadline = time.monotonic() + forever
        while time.monotonic() < deadline:
            pass
    elif fault in ("sleep", "await"):
        time.sleep(forever)
    elif fault == "thread":
        threading.Thread(target=time.sleep, args=(forever,), name=f"leaked-by-{where}").start()
    elif fault == "slow":
        time.sleep(SLOW_S)


async def _misbehave(fault: str, where: str, forever: float = FOREVER_S) -> None:
    if fault == "await":
        print(f"misbehaving: {fault} in {where}", flush=True)
        await asyncio.sleep(forever)
    elif fault == "slow":
        await asyncio.sleep(SLOW_S)
    else:
        _misbehave_plainly(fault, where, forever)


class Faulty(LifecycleNode):
    """A lifecycle node whose plain callbacks go wrong where its parameters say."""

    default_node_name = "faulty"

    def __init__(self, node_name: str = default_node_name, **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self.fault = str(self.declare_parameter("fault", "raise").value)
        self.where = str(self.declare_parameter("where", "timer").value)
        #: How long "forever" lasts for this node, in seconds.
        self.forever = float(self.declare_parameter("forever", FOREVER_S).value)
        if self.where == "constructor":
            _misbehave_plainly(self.fault, self.where, self.forever)
        self.hits = 0
        if self.where == "timer":
            self.create_timer(0.05, self._tick)
        elif self.where == "subscription":
            self.create_subscription(String, "~/poke", self._poked, 10)
        elif self.where == "service":
            self.create_service(Trigger, "~/poke", self._serve)

    def _once(self) -> bool:
        self.hits += 1
        return self.hits == 1

    def _tick(self) -> None:
        if self._once():
            _misbehave_plainly(self.fault, self.where, self.forever)

    def _poked(self, message: String) -> None:
        self._tick()

    def _serve(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        self._tick()
        response.success = True
        return response

    def _transition(self, label: str) -> TransitionCallbackReturn:
        if label == self.where:
            _misbehave_plainly(self.fault, label, self.forever)
        return TransitionCallbackReturn.SUCCESS

    def on_configure(self, state: LifecycleState) -> TransitionOutcome:
        return self._transition("configure")

    def on_activate(self, state: LifecycleState) -> TransitionOutcome:
        return self._transition("activate")

    def on_deactivate(self, state: LifecycleState) -> TransitionOutcome:
        return self._transition("deactivate")

    def on_cleanup(self, state: LifecycleState) -> TransitionOutcome:
        return self._transition("cleanup")

    def on_shutdown(self, state: LifecycleState) -> TransitionOutcome:
        return self._transition("shutdown")


class FaultyAsync(Faulty):
    """The same, with ``async def`` callbacks and transitions."""

    default_node_name = "faulty_async"

    async def _tick(self) -> None:  # type: ignore[override]
        if self._once():
            await _misbehave(self.fault, self.where, self.forever)

    async def _poked(self, message: String) -> None:  # type: ignore[override]
        await self._tick()

    async def _serve(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        await self._tick()
        response.success = True
        return response

    async def _transition_async(self, label: str) -> TransitionCallbackReturn:
        if label == self.where:
            await _misbehave(self.fault, label, self.forever)
        return TransitionCallbackReturn.SUCCESS

    async def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        return await self._transition_async("configure")

    async def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        return await self._transition_async("activate")

    async def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        return await self._transition_async("deactivate")

    async def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        return await self._transition_async("cleanup")

    async def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        return await self._transition_async("shutdown")


@hookimpl
def register_node_types(register: RegisterNodeType) -> None:
    """Register ``tests_faults::Faulty`` and ``tests_faults::FaultyAsync``."""
    register(Faulty)
    register(FaultyAsync)
