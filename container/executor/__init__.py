"""The executor: rclpy's ``Executor`` contract on an asyncio event loop.

Start reading at :class:`AsyncioExecutor` (``_executor``). Under it, in the
order work flows: ``_selector`` (the loop's thread sleeps in ``rcl_wait``),
``_dispatch`` (cached wait sets; what is ready goes to a lane), ``_lanes``
(callback groups: worker threads for plain callbacks, runner tasks for
``async def`` ones) and ``_bridge`` (rclpy futures seen from asyncio;
``_spare`` keeps the threads its ``in_thread`` calls run on). This
package depends on rclpy and :mod:`container._compat` only, never on the
rest of the container.
"""

from ._accounting import Accounting, CallbackLoad, ContainerLoad, GroupLoad, NodeLoad, UnattributedLoad
from ._answers import end_resender
from ._bridge import Escaped, contained, in_thread, result
from ._culprit import working_for
from ._engine import Deadline
from ._entries import describe
from ._executor import AsyncioExecutor, CallbackErrorHandler, ExecutorState
from ._frames import format_plugin_frames
from ._inbox import call_soon, run_coroutine
from ._message_info import HAS_PUBLISHER_GID, publisher_gid
from ._spare import end_spare_threads

# The executor's API, then what the rest of the container shares with it:
# running plugin code (``Escaped``, ``contained``, ``in_thread``, and
# ``end_spare_threads`` for the threads ``in_thread`` keeps, ``end_resender``
# for the thread that sends answers to clients not known to be matched, and
# ``Deadline`` to end the process where no Python thread may run), awaiting
# an rclpy future (``result``), posting to a loop from another thread
# (``call_soon``, ``run_coroutine``: the one way, see ``_inbox``), naming a
# callback in a log (``describe``), showing a plugin's own frames of a stack
# (``format_plugin_frames``) and counting loop work as a node's for the
# watchdog (``working_for``).
__all__ = [
    "HAS_PUBLISHER_GID",
    "Accounting",
    "AsyncioExecutor",
    "CallbackErrorHandler",
    "CallbackLoad",
    "ContainerLoad",
    "Deadline",
    "Escaped",
    "ExecutorState",
    "GroupLoad",
    "NodeLoad",
    "UnattributedLoad",
    "call_soon",
    "contained",
    "describe",
    "end_resender",
    "end_spare_threads",
    "format_plugin_frames",
    "in_thread",
    "publisher_gid",
    "result",
    "run_coroutine",
    "working_for",
]
