"""A service's requests and answers, and a client's responses (``fastpath/service.c``).

The compiled ``Server`` and ``Caller`` take into C messages kept across
takes and send without rclpy's wrapper (its three calls of a round trip
took 16 us, these 8-10 us). Here they are rclpy's own handle calls
(``service_take_request``, ``service_send_response``, ``take_response``)
on handles held and entered, with the same answers: ``(request, header)``,
``(sequence_number, response)``, ``None`` when nothing waits, ``False`` from
:meth:`Server.send` while the client's response reader is not matched (yet),
the same ``TypeError`` for a response of another type.

The header is opaque to the caller: bytes of ``rmw_request_id_t`` in C,
rclpy's request id object here; :meth:`Server.send` takes only what
:meth:`Server.take` gave.

Differences: a take makes a new C message each time (rclpy's), where the
compiled ones keep one across takes; rmw's wait for an unmatched client (Fast DDS: up to 100 ms)
holds the GIL whatever ``let_go`` asks (rclpy's call keeps it: the resender,
``_answers``, tries only a client the graph shows compatible), and rclpy
tells an unmatched client by a ``RuntimeWarning`` or an ``RCLError``
(``container._compat.client_not_matched``), where C reads rcl's return code;
the client's GUID, which the compiled header carries in its bytes, is read
from behind rclpy's header (``container._compat.request_client``).
"""

from __future__ import annotations

from typing import Any

from ..._compat import RequestId, client_not_matched, raise_client_not_matched
from .held import Held, check_message_type

__all__ = ["Caller", "Server"]

# rclpy reports an unmatched client as a warning, which only an error lets this see.
raise_client_not_matched()


class Server:
    """One service's requests and its answers (its handle held)."""

    __slots__ = ("_request_type", "_response_type", "_service")

    def __init__(self, *, service: Any, srv_type: type) -> None:
        if getattr(self, "_service", None) is not None:
            raise RuntimeError("Server is initialised once")
        request_type = srv_type.Request  # type: ignore[attr-defined]
        check_message_type(request_type)
        response_type = srv_type.Response  # type: ignore[attr-defined]
        check_message_type(response_type, from_py=True)
        self._request_type: type = request_type
        self._response_type: type = response_type
        self._service: Held | None = Held(service)

    def close(self) -> None:
        """Let the handle go; a take or send after this raises ``RuntimeError``."""
        held, self._service = self._service, None
        if held is not None:
            held.exit()

    @property
    def closed(self) -> bool:
        """Whether :meth:`close` let the handle go (rclpy's calls serve it then)."""
        return self._service is None

    def _handle(self) -> Any:
        held = self._service
        if held is None:
            raise RuntimeError("Server not initialised, or closed")
        return held.handle

    def take(self) -> tuple[Any, Any] | None:
        """``(request, header)``, or ``None``; the header is for :meth:`send` only."""
        request, info = self._handle().service_take_request(self._request_type)
        if info is None:
            return None
        return request, info.request_id

    def send(self, response: Any, header: Any, let_go: bool = False, /) -> bool:
        """Answer the request ``header`` came with: ``False`` while the client's response
        reader is not matched (rmw waits up to 100 ms for it, GIL held here);
        ``TypeError`` for a response of another type."""
        handle = self._handle()
        if not isinstance(header, RequestId):
            raise ValueError("not a header from take()")
        if not isinstance(response, self._response_type):
            raise TypeError(
                f"a service callback returned {type(response).__name__}, not {self._response_type.__name__}"
            )
        try:
            handle.service_send_response(response, header)
        except Exception as error:
            if client_not_matched(error):
                return False
            raise
        return True


class Caller:
    """One client's responses (its handle held)."""

    __slots__ = ("_client", "_response_type")

    def __init__(self, *, client: Any, srv_type: type) -> None:
        if getattr(self, "_client", None) is not None:
            raise RuntimeError("Caller is initialised once")
        response_type = srv_type.Response  # type: ignore[attr-defined]
        check_message_type(response_type)
        self._response_type: type = response_type
        self._client: Held | None = Held(client)

    def close(self) -> None:
        """Let the handle go; a take after this raises ``RuntimeError``."""
        held, self._client = self._client, None
        if held is not None:
            held.exit()

    def take(self) -> tuple[int, Any] | None:
        """``(sequence_number, response)``, or ``None``."""
        held = self._client
        if held is None:
            raise RuntimeError("Caller not initialised, or closed")
        info, response = held.handle.take_response(self._response_type)
        if info is None:
            return None
        return int(info.request_id.sequence_number), response
