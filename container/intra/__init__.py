"""Intra-process communication: nodes of one container exchange messages without DDS.

A node joins with ``use_intra_process_comms`` (a LoadNode extra argument, a
node's ``extra_arguments`` in the container file, ``container.
use_intra_process_comms`` as the file's default, ``LifecycleNode(...,
use_intra_process_comms=True)`` or :func:`enable_intra_process` in code).
Its class does the joining: :class:`IntraProcessNode` (which
:class:`~container.LifecycleNode` is) creates its publishers and
subscriptions in the context's domain; the container hosts any other node
class as its :func:`intra_process_class`.
Between such nodes a message is copied once (:func:`copy_message`, about a
tenth of a serialisation) and shared read-only by every subscription in
process; :func:`hand_over` shares the object itself. Everyone else gets it
over DDS, and no subscription gets a message twice. The README's
"Intra-process communication" states the contract.
"""

from __future__ import annotations

from ._copy import copy_message
from ._node import IntraProcessNode, enable_intra_process, hand_over, intra_process_class, intra_process_enabled

__all__ = [
    "IntraProcessNode",
    "copy_message",
    "enable_intra_process",
    "hand_over",
    "intra_process_class",
    "intra_process_enabled",
]
