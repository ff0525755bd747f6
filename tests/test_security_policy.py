"""The SROS2 policy shipped for the LiDAR example covers what the container really serves.

A DDS permissions file denies whatever it does not name: a policy that
misses one service of the container would break it only once security is on
(which this machine's Fast DDS cannot do). So the policy's profiles are
compared with the ROS graph of a running ``container run examples/lidar.yaml``.
"""

from __future__ import annotations

import time
import xml.etree.ElementTree as ElementTree
from collections.abc import Callable
from pathlib import Path

import pytest
from rclpy.node import Node

from tests.container_support import REPO, ContainerProcess

POLICY = REPO / "examples" / "security" / "lifecycle_container.policy.xml"


def _resolve(name: str, *, node: str, namespace: str) -> str:
    if name.startswith("~"):
        return f"{namespace.rstrip('/')}/{node}{name[1:]}"
    return name if name.startswith("/") else f"{namespace.rstrip('/')}/{name}"


def _profile(enclave: str, node: str) -> dict[str, set[str]]:
    """What one profile allows, as absolute names: ``reply``, ``request``, ``publish``, ``subscribe``."""
    root = ElementTree.parse(POLICY).getroot()
    assert root.tag == "policy" and root.get("version") == "0.2.0"
    [element] = [
        profile
        for found in root.iter("enclave")
        if found.get("path") == enclave
        for profile in found.iter("profile")
        if profile.get("node") == node
    ]
    namespace = element.get("ns", "/")
    allowed: dict[str, set[str]] = {"reply": set(), "request": set(), "publish": set(), "subscribe": set()}
    for group in element:
        for rule, names in allowed.items():
            if group.get(rule) == "ALLOW":
                names.update(_resolve(item.text or "", node=node, namespace=namespace) for item in group)
    return allowed


def _graph(observer: Node, node: str, namespace: str) -> dict[str, set[str]]:
    return {
        "reply": {n for n, _ in observer.get_service_names_and_types_by_node(node, namespace)},
        "publish": {n for n, _ in observer.get_publisher_names_and_types_by_node(node, namespace)},
        "subscribe": {n for n, _ in observer.get_subscriber_names_and_types_by_node(node, namespace)},
    }


# A container process with a LiDAR.
@pytest.mark.slow
def test_the_policy_names_every_service_and_topic_of_the_lidar_container(
    run_container: Callable[..., ContainerProcess], client_node: Node
) -> None:
    proc = run_container((REPO / "examples" / "lidar.yaml").read_text())
    proc.wait_for_line("Loaded ldlidar::LdLidarNode")
    deadline = time.monotonic() + 20
    wanted = {"ComponentManager": "/ComponentManager/_container/load_node", "ldlidar": "/ldlidar/scan"}
    graphs: dict[str, dict[str, set[str]]] = {}
    while True:
        present = {name for name, namespace in client_node.get_node_names_and_namespaces() if namespace == "/"}
        if not set(wanted) <= present:
            assert time.monotonic() < deadline, f"the container's nodes never showed up: {sorted(present)}"
            time.sleep(0.1)
            continue
        graphs = {node: _graph(client_node, node, "/") for node in wanted}
        if all(name in graphs[node]["reply"] | graphs[node]["publish"] for node, name in wanted.items()):
            break
        assert time.monotonic() < deadline, f"the container's graph never showed up: {graphs}"
        time.sleep(0.1)

    for node, graph in graphs.items():
        allowed = _profile("/lifecycle_container", node)
        for rule, names in graph.items():
            missing = names - allowed[rule]
            assert not missing, f"{node}: {rule} not in the policy: {sorted(missing)}"


def test_the_operators_enclave_may_call_what_the_command_line_calls() -> None:
    operator = _profile("/lifecycle_container_operator", "operator")
    container = _profile("/lifecycle_container", "ComponentManager")
    lidar = _profile("/lifecycle_container", "ldlidar")
    assert {n for n in container["reply"] if "/_container/" in n} <= operator["request"]
    assert {f"/ldlidar/{s}" for s in ("change_state", "get_state", "get_available_transitions")} <= operator["request"]
    assert operator["request"] <= container["reply"] | lidar["reply"]
    # container top reads what the container publishes of its nodes' load.
    assert {"/ComponentManager/load"} <= operator["subscribe"] <= container["publish"] | lidar["publish"]


def test_the_policy_file_is_the_one_the_security_guide_points_at() -> None:
    guide = (REPO / "docs" / "guide" / "security.md").read_text()
    assert str(POLICY.relative_to(REPO)) in guide
    assert Path(POLICY).is_file()
