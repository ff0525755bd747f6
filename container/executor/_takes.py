"""Taking what rcl has ready and handing it to the dispatcher, per kind of entity.

Each function takes everything its entity has waiting, at once (rcl wait
sets are level-triggered, and a service's requests sit in a keep-last
history that twenty peers asking at once would overflow), and submits each
callback invocation to the entity's lane through the dispatcher.
"""

from __future__ import annotations

import functools
import itertools
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from rclpy.exceptions import InvalidHandle
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile

from .._compat import (
    adopt_future,
    fire_timer,
    waitable_futures,
)
from . import _engine
from ._answers import respond
from ._engine import Server
from ._entries import Entry

if TYPE_CHECKING:
    from ._dispatch import Dispatcher

__all__: list[str] = []

#: Empty takes a keep-all client goes through before its reader counts as
#: drained (see :func:`take_response`).
_KEEP_ALL_DRAINED = 1024


def take_timer(dispatcher: Dispatcher, entry: Entry) -> None:
    tmr = entry.entity
    late_ns = 0
    try:
        with tmr.handle:
            if entry.meter is not None:
                # Due that long ago: its lateness counts from then, not from this take.
                until = tmr.handle.time_until_next_call()
                late_ns = -until if until is not None and until < 0 else 0
            arguments = fire_timer(tmr)
    except InvalidHandle:
        return
    if arguments is None:
        return
    if arguments:
        dispatcher.submit(entry, functools.partial(tmr.callback, **arguments), (), late_ns=late_ns)
    else:
        dispatcher.submit(entry, tmr.callback, (), late_ns=late_ns)

def take_messages(dispatcher: Dispatcher, entry: Entry, count: int) -> None:
    """Take up to ``count`` messages: what its new-data callbacks reported (fewer if
    DDS dropped some), or one for a subscription a wait found ready."""
    sub = entry.entity
    callback = sub.callback
    submit = dispatcher.submit
    taker = entry.taker
    with_info = entry.wants_info
    if taker is None:
        msg_type, raw = sub.msg_type, sub.raw
        for _ in range(count):
            taken = sub.handle.take_message(msg_type, raw)
            if taken is None:
                return
            submit(entry, callback, tuple(taken) if with_info else (taken[0],))
    elif with_info:
        for _ in range(count):
            pair = taker.take_with_info()
            if pair is None:
                return
            submit(entry, callback, pair)
    else:
        for _ in range(count):
            message = taker.take()
            if message is None:
                return
            submit(entry, callback, (message,))

def take_response(dispatcher: Dispatcher, entry: Entry, count: int = _engine.DRAIN) -> None:
    """Take ``count`` times (what the new-response callbacks reported), or
    every response waiting (a wait found the client ready; a fresh watch).

    A client's reader receives the responses to every client of its
    service, and a take of another client's response takes nothing
    (rmw drops it): only a count of takes reaches this client's own
    response behind those. Stopping at the first empty take left it in
    the reader, with no callback to come: a caller among twenty waited
    forever, about once in thirty runs. Without a count, an empty take
    is either, so taking goes on until as many empty takes as the
    reader holds responses.
    """
    cli = entry.entity
    caller = entry.caller
    drain = count >= _engine.DRAIN
    empty_left = _held_at_most(cli.qos_profile) if drain else 0
    for _ in itertools.repeat(None) if drain else range(count):
        if caller is not None:
            # The wait set holds the client's handle while it can be taken.
            taken = caller.take()
        else:
            try:
                with cli.handle:
                    header, response = cli.handle.take_response(cli.srv_type.Response)
            except InvalidHandle:
                return
            taken = None if header is None else (header.request_id.sequence_number, response)
        if taken is None:
            if drain:
                empty_left -= 1
                if empty_left <= 0:
                    return
            continue  # another client's response (or, draining, none left)
        sequence, response = taken
        try:
            future = cli.get_pending_request(sequence)
        except KeyError:
            continue  # the caller cancelled the request
        adopt_future(future, dispatcher.response_executor)
        if entry.owner is None:
            future.set_result(response)
        else:
            # Its done-callbacks (the node's code, handed to the executor) run as its node's:
            # told to where they are handed, cheaper than setting ``OWNER`` and back.
            done = dispatcher.response_executor
            done.owner = entry.owner
            try:
                future.set_result(response)
            finally:
                done.owner = None
        dispatcher.response_arrived()

def take_request(dispatcher: Dispatcher, entry: Entry, count: int = _engine.DRAIN) -> None:
    """Take ``count`` requests (what the new-request callbacks reported), or
    every request waiting (a wait found the service ready; a fresh watch),
    each to be answered.

    All at once, not one per wait: service requests sit in a keep-last
    history (depth 10 by default), and twenty peers asking at once would
    otherwise lose the oldest before their turn came. With a count, no
    take comes back empty to say so: 1.5 us of a 40 us round trip.
    """
    srv = entry.entity
    server = entry.server
    serve = _serve_async if entry.is_async else _serve
    callback, request_type, response_type = srv.callback, srv.srv_type.Request, srv.srv_type.Response
    for _ in itertools.repeat(None) if count >= _engine.DRAIN else range(count):
        if server is not None:
            # The wait set holds the service's handle while it can be taken.
            taken = server.take()
            if taken is None:
                return
            request, header = taken
        else:
            try:
                with srv.handle:
                    request, header = srv.handle.service_take_request(request_type)
            except InvalidHandle:
                return
            if header is None:
                return
        dispatcher.submit(entry, serve, (srv, server, entry.node, callback, response_type, request, header))

def take_waitable(dispatcher: Dispatcher, entry: Entry) -> None:
    waitable = entry.entity
    try:
        data = waitable.take_data()
    except Exception as error:
        dispatcher.waitable_failed(waitable, entry.node, "take_data()", error)
        return
    for future in waitable_futures(waitable):
        adopt_future(future, dispatcher.future_executor)

    async def execute() -> None:
        await waitable.execute(data)

    dispatcher.run(entry, execute)


def _held_at_most(qos: QoSProfile) -> int:
    """How many samples a reader with ``qos`` holds at most (keep-all: a bound of ours)."""
    if qos.history == HistoryPolicy.KEEP_LAST and qos.depth > 0:
        return int(qos.depth)
    return _KEEP_ALL_DRAINED



async def _serve_async(
    srv: Any,
    server: Server | None,
    node: Node,
    callback: Callable[..., Any],
    response_type: type,
    request: Any,
    header: Any,
) -> None:
    """Run an ``async def`` service callback on ``request`` and send its answer.

    A module function given its arguments, not a closure made per request:
    a closure and its coroutine function cost a few percent of a service
    round trip."""
    respond(srv, await callback(request, response_type()), header, server=server, node=node)


def _serve(
    srv: Any,
    server: Server | None,
    node: Node,
    callback: Callable[..., Any],
    response_type: type,
    request: Any,
    header: Any,
) -> None:
    """Run a plain service callback on ``request`` and send its answer."""
    respond(srv, callback(request, response_type()), header, server=server, node=node)
