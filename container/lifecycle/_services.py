"""A lifecycle node's standard services, served keep-all like the container's own, answers paced.

rcl's lifecycle state machine can create ``<node>/change_state``,
``get_state``, ``get_available_states``, ``get_available_transitions`` and
``get_transition_graph`` itself, but only with rcl's default service QoS
(keep-last 10): neither rcl_lifecycle nor rclpy's ``LifecycleStateMachine``
(rclpy 7 and 9: ``LifecycleStateMachine(node, enable_com_interface)``, no
options) takes another. Twenty ``change_state`` callers at once then got 10
of 20 answers: the requests beyond ten were overwritten before the service
took them.

So :class:`~container.LifecycleNode` asks rcl for a state machine without
them (``enable_communication_interface=False``; rcl still creates
``transition_event`` and publishes every transition on it, as before) and
:class:`LifecycleServices` serves them: the same names and types, answered
from the same state machine as rclpy's handlers answer, with the container
services' QoS (:data:`container._qos.SERVICE_QOS`: keep-all, reliable,
volatile, which clients with rclpy's default QoS match). Every request is
taken then; the answers of a burst are spaced (:mod:`._pacing`), since each
client receives every answer of the service and keeps only its last 10.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import TYPE_CHECKING, Any

from lifecycle_msgs.msg import State, TransitionDescription
from lifecycle_msgs.srv import ChangeState, GetAvailableStates, GetAvailableTransitions, GetState
from rclpy.callback_groups import ReentrantCallbackGroup

from .._qos import SERVICE_QOS
from ._pacing import AnswerPacer, paced

if TYPE_CHECKING:
    from rclpy.node import Node
    from rclpy.service import Service

__all__ = ["LifecycleServices"]

#: The names rcl_lifecycle gives them (``com_interface.c``), relative to the node.
CHANGE_STATE = "~/change_state"
GET_STATE = "~/get_state"
GET_AVAILABLE_STATES = "~/get_available_states"
GET_AVAILABLE_TRANSITIONS = "~/get_available_transitions"
GET_TRANSITION_GRAPH = "~/get_transition_graph"

#: Reads the node's state machine: ``read("current_state")``.
Reader = Callable[[str], Any]

ChangeStateHandler = Callable[[ChangeState.Request, ChangeState.Response], ChangeState.Response]


class LifecycleServices:
    """Serve a lifecycle node's five standard services, keep-all, their answers paced.

    ``change_state`` goes to the node's default callback group, as rclpy
    puts it: the node decides how transitions are ordered. The four queries
    only read, and share a reentrant group of their own, so that ``ros2
    lifecycle get`` answers "configuring" while a transition awaits. Each
    service spaces its answers in a burst (:mod:`._pacing`): every client
    of a service receives every answer, and keeps only 10 by default.

    :param node: the lifecycle node to serve them on; they live as long as it does.
    :param read: reads an attribute of the node's rcl state machine, holding it.
    :param change_state: the ``change_state`` handler.
    """

    def __init__(self, node: Node, *, read: Reader, change_state: ChangeStateHandler) -> None:
        self._read = read
        queries = ReentrantCallbackGroup()
        #: The ``change_state`` service (whose work the loop's watchdog names).
        self.change_state: Service[Any, Any] = node.create_service(
            ChangeState, CHANGE_STATE, paced(change_state, AnswerPacer()), qos_profile=SERVICE_QOS
        )
        served: list[tuple[type[Any], str, Callable[[Any, Any], Any]]] = [
            (GetState, GET_STATE, self._get_state),
            (GetAvailableStates, GET_AVAILABLE_STATES, self._get_available_states),
            (GetAvailableTransitions, GET_AVAILABLE_TRANSITIONS, self._get_available_transitions),
            (GetAvailableTransitions, GET_TRANSITION_GRAPH, self._get_transition_graph),
        ]
        #: ``get_state``, ``get_available_states``, ``get_available_transitions``, ``get_transition_graph``.
        self.queries: tuple[Service[Any, Any], ...] = tuple(
            node.create_service(
                srv_type, name, paced(handler, AnswerPacer()), qos_profile=SERVICE_QOS, callback_group=queries
            )
            for srv_type, name, handler in served
        )

    # Plain callbacks: they answer from a lane's thread even while an
    # ``async def`` transition callback holds the event loop.
    def _get_state(self, request: GetState.Request, response: GetState.Response) -> GetState.Response:
        state_id, label = self._read("current_state")
        response.current_state = State(id=state_id, label=label)
        return response

    def _get_available_states(
        self, request: GetAvailableStates.Request, response: GetAvailableStates.Response
    ) -> GetAvailableStates.Response:
        states = self._read("available_states")
        response.available_states = [State(id=state_id, label=label) for state_id, label in states]
        return response

    def _get_available_transitions(
        self, request: GetAvailableTransitions.Request, response: GetAvailableTransitions.Response
    ) -> GetAvailableTransitions.Response:
        response.available_transitions = _descriptions(self._read("available_transitions"))
        return response

    def _get_transition_graph(
        self, request: GetAvailableTransitions.Request, response: GetAvailableTransitions.Response
    ) -> GetAvailableTransitions.Response:
        response.available_transitions = _descriptions(self._read("transition_graph"))
        return response


def _descriptions(transitions: Iterable[tuple[int, str, int, str, int, str]]) -> list[TransitionDescription]:
    """Messages for rcl's ``(id, label, start id, start label, goal id, goal label)`` tuples."""
    described = []
    for transition_id, label, start_id, start_label, goal_id, goal_label in transitions:
        item = TransitionDescription()
        item.transition.id = transition_id
        item.transition.label = label
        item.start_state = State(id=start_id, label=start_label)
        item.goal_state = State(id=goal_id, label=goal_label)
        described.append(item)
    return described
