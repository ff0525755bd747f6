"""The QoS every service the container serves itself is created with.

Shared by the container services (``~/_container/load_node`` ...) and the
standard services of every hosted lifecycle node (``<node>/change_state``
...): both are called in bursts by tools, launch files and lifecycle
managers, and both must answer every caller.
"""

from __future__ import annotations

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

__all__ = ["SERVICE_QOS"]

#: rclpy's services default (reliable, volatile) but keeping every request
#: and every answer. With the default's keep-last 10, a burst of requests
#: lost most of them inside DDS, the request history overwritten before the
#: service took them and answers before the clients acknowledged them:
#: their callers waited for good (500 ``LoadNode`` requests from five
#: clients: 37 answered; 20 concurrent ``change_state`` callers: 10 to 20
#: answered). Keep-all bounds them by Fast DDS's resource limits instead
#: (5,000 samples by default). Keep-all and keep-last match each other, so
#: clients keep their default QoS.
SERVICE_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_ALL,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)
