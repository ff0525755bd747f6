"""Lifecycle nodes and their management: the node base, transitions, faults, the manager.

``_node`` is the :class:`LifecycleNode` base plugins subclass; ``_transitions``
drives a hosted node up and down; ``_faults`` sends a node whose callback
raised through error processing; ``_heartbeat`` and ``_client`` are what the
Nav2-compatible :class:`LifecycleManager` (``_manager``) watches and calls.
Depends on :mod:`container.executor`; the container proper depends on this.
"""

from ._client import LifecycleClient
from ._faults import contain_fault
from ._manager import LifecycleManager, ManagerSettings
from ._node import LifecycleNode
from ._transitions import bring_down, bring_up, is_lifecycle, state_of, transition

# The public API, then what the container, its command line and its test
# fixtures share: driving a node through its services (``LifecycleClient``)
# or in process (the rest).
__all__ = [
    "LifecycleClient",
    "LifecycleManager",
    "LifecycleNode",
    "ManagerSettings",
    "bring_down",
    "bring_up",
    "contain_fault",
    "is_lifecycle",
    "state_of",
    "transition",
]
