"""The container as ROS tools find and start it: the ament index, launch_ros's arguments and requests.

ros2cli and launch_ros are not on PyPI; ament_index_python (what both look
packages up with) is. These tests do what they do, step by step:

* ``ros2 pkg list`` / ``ros2 run`` / launch_ros's ``ExecutableInPackage``:
  the package's prefix from the index, then ``<prefix>/lib/<package>/<executable>``;
* ``ros2 component types``: the ``rclcpp_components`` resource of each
  package, the part of each line before ``;``;
* launch_ros's ``ComposableNodeContainer``: the executable started with
  ``--ros-args -r __node:=NAME -r __ns:=/NS --params-file FILE``, then one
  LoadNode request per ``ComposableNode`` with what
  ``get_composable_node_load_request`` puts in it.
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from ament_index_python import (
    get_package_prefix,
    get_packages_with_prefixes,
    get_resource,
    get_resources,
    has_resource,
)
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState, GetState
from rcl_interfaces.srv import GetParameters
from rclpy.client import Client
from rclpy.node import Node

from container import AsyncioExecutor
from container._ament import EXECUTABLES, PROJECT_PACKAGE, RECORD_TYPE, installed_prefix, write_index
from container._registry import NodeType, PluginRegistry
from tests.component_support import IMPORT_ROOT, ContainerClient, install_test_plugin
from tests.container_support import REPO
from tests.process_support import (
    VENV_ACTIVATE,
    LoggedProcess,
    composable_node_request,
    container_command,
    executable_in_package,
    launch_params_file,
)


def executables_of(package: str) -> set[str]:
    """ros2pkg's get_executable_paths: every executable file under <prefix>/lib/<package>."""
    base = os.path.join(get_package_prefix(package), "lib", package)
    return {
        name
        for directory, _, files in os.walk(base)
        for name in files
        if os.access(os.path.join(directory, name), os.X_OK)
    }


def component_types() -> dict[str, list[str]]:
    """ros2component's get_registered_component_types, as `ros2 component types` prints it."""
    listing = {}
    for package in get_resources("rclcpp_components"):
        assert has_resource("rclcpp_components", package)
        content, _ = get_resource("rclcpp_components", package)
        listing[package] = [line.split(";")[0] for line in content.splitlines()]
    return listing


def test_activation_puts_the_venv_on_the_ament_prefix_path(ament_prefix_path: str) -> None:
    assert ament_prefix_path.split(os.pathsep)[0] == sys.prefix
    deactivated = subprocess.run(
        ["bash", "-c", f'export AMENT_PREFIX_PATH=/opt/ros/jazzy; . "{VENV_ACTIVATE}"; '
         'printf "%s\\n" "$AMENT_PREFIX_PATH"; deactivate; printf "%s\\n" "$AMENT_PREFIX_PATH"'],
        capture_output=True, text=True, timeout=30, check=True,
    )
    assert deactivated.stdout == f"{sys.prefix}:/opt/ros/jazzy\n/opt/ros/jazzy\n"


def test_the_container_command_sets_the_ament_prefix_path_for_what_it_starts() -> None:
    env = {k: v for k, v in os.environ.items() if k != "AMENT_PREFIX_PATH"}
    script = "import os; from container.cli import use_this_ament_prefix; use_this_ament_prefix(); " \
        "print(os.environ['AMENT_PREFIX_PATH'])"
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60, env=env)
    assert result.stdout.split(os.pathsep)[0].strip() == sys.prefix, result.stderr


def test_packages_executables_and_types_resolve_as_ros_tools_resolve_them(ament_prefix_path: str) -> None:
    registry = PluginRegistry()
    packages = get_packages_with_prefixes()  # ros2 pkg list
    for package in [PROJECT_PACKAGE, *registry.packages()]:
        assert packages.get(package) == sys.prefix, f"{package} is not a package of {sys.prefix}"
    # ros2 run lifecycle_container <TAB>, and what launch_ros starts.
    assert executables_of(PROJECT_PACKAGE) == set(EXECUTABLES)
    for executable in EXECUTABLES:
        assert executable_in_package(PROJECT_PACKAGE, executable) == os.path.join(
            sys.prefix, "lib", PROJECT_PACKAGE, executable
        )
    # ros2 component types lists what `container types` lists.
    listed = component_types()
    assert {package: sorted(types) for package, types in listed.items()} == registry.packages()
    result = subprocess.run(
        [sys.executable, "-m", "container", "types"], capture_output=True, text=True, timeout=60, cwd=REPO
    )
    printed = "".join(
        package + "\n" + "".join(f"  {name}\n" for name in sorted(types)) for package, types in sorted(listed.items())
    )
    assert result.stdout == printed


# Indexes and ROS tools in child processes.
@pytest.mark.slow
def test_index_adds_a_new_plugin_and_removes_it_when_it_is_gone(tmp_path: Path) -> None:
    prefix = tmp_path / "prefix"
    foreign = prefix / "share" / "ament_index" / "resource_index" / "packages" / "test_nodes_foreign"
    foreign.parent.mkdir(parents=True)
    foreign.touch()  # some other installation's package
    site = install_test_plugin(tmp_path / "site", distribution="test-nodes")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(site), str(IMPORT_ROOT)]))

    def index(env: dict[str, str]) -> str:
        result = subprocess.run(
            [sys.executable, "-m", "container", "index", "--prefix", str(prefix)],
            capture_output=True, text=True, timeout=60, env=env, cwd=REPO,
        )
        assert result.returncode == 0, result.stderr
        return result.stdout

    assert "test_nodes: 4 node type(s)" in index(env)
    env_prefix = dict(os.environ, AMENT_PREFIX_PATH=str(prefix))
    check = (
        "from ament_index_python import get_packages_with_prefixes as p, get_resource as r;"
        "print(sorted(p())); print(r('rclcpp_components', 'test_nodes')[0] if 'test_nodes' in p() else '')"
    )
    listing = subprocess.run([sys.executable, "-c", check], capture_output=True, text=True, env=env_prefix, timeout=60)
    assert "'test_nodes'" in listing.stdout and "'test_nodes_foreign'" in listing.stdout, listing.stderr
    assert "test_nodes::Busy;tests.component_support:Busy\ntest_nodes::Exploding;" in listing.stdout
    assert "up to date" in index(env)

    gone = index(dict(os.environ))  # the plugin uninstalled
    assert "test_nodes: removed (no longer installed in this prefix)" in gone
    index_dir = prefix / "share" / "ament_index" / "resource_index"
    assert not (index_dir / "packages" / "test_nodes").exists()
    assert not (index_dir / "rclcpp_components" / "test_nodes").exists()
    assert foreign.exists()
    # The container's own package is the prefix it is installed in's, never this one's.
    assert not (prefix / "lib" / PROJECT_PACKAGE).exists()
    assert not (index_dir / "packages" / PROJECT_PACKAGE).exists()


def installed_plugin(prefix: Path, monkeypatch: pytest.MonkeyPatch, distribution: str) -> list[NodeType]:
    """``distribution`` installed into ``prefix`` as colcon installs a plugin (its metadata in the
    prefix's site-packages, on ``sys.path``): its node types."""
    site = prefix / "lib" / f"python{sys.version_info.major}.{sys.version_info.minor}" / "site-packages"
    install_test_plugin(site, distribution=distribution)
    monkeypatch.syspath_prepend(str(site))
    return [t for t in PluginRegistry().types.values() if t.distribution == distribution]


def files_under(root: Path) -> dict[str, bytes]:
    return {str(path.relative_to(root)): path.read_bytes() for path in root.rglob("*") if path.is_file()}


def test_an_existing_ros_package_of_the_same_name_is_left_alone(tmp_path: Path) -> None:
    index_dir = tmp_path / "share" / "ament_index" / "resource_index"
    (index_dir / "packages").mkdir(parents=True)
    (index_dir / "packages" / "test_nodes").touch()  # some other installation's package
    site = install_test_plugin(tmp_path / "elsewhere", distribution="test-nodes")
    sys.path.insert(0, str(site))
    try:
        report = write_index(tmp_path, PluginRegistry().types.values(), project=None)
    finally:
        sys.path.remove(str(site))
    assert ("test_nodes", f"a ROS package named 'test_nodes' is already installed in {tmp_path}") in report.skipped
    assert not (index_dir / "rclcpp_components" / "test_nodes").exists()


def test_a_named_plugin_is_registered_in_its_prefix_beside_the_package_marker_colcon_wrote(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # `container index --prefix install/my_robot --distribution my_robot` after
    # `colcon build` of an ament_python plugin: the marker is the package's own.
    prefix = tmp_path / "install" / "my_robot"
    index_dir = prefix / "share" / "ament_index" / "resource_index"
    (index_dir / "packages").mkdir(parents=True)
    (index_dir / "packages" / "my_robot").touch()
    types = installed_plugin(prefix, monkeypatch, "my-robot")
    assert installed_prefix("my-robot") == prefix.resolve()

    report = write_index(prefix, types, project=None, prune=False, strict=True)

    assert (report.skipped, list(report.registered)) == ([], ["my_robot"])
    assert (index_dir / "rclcpp_components" / "my_robot").read_text().splitlines()[0] == (
        "my_robot::Burner;tests.component_support:Burner"
    )
    # Nothing of the container's own package: its prefix is the one it is installed in.
    assert sorted(path.name for path in index_dir.iterdir()) == ["lifecycle_container_plugins", "packages",
                                                                 "rclcpp_components"]
    assert [path.name for path in (index_dir / "packages").iterdir()] == ["my_robot"]
    assert not (prefix / "lib" / PROJECT_PACKAGE).exists()
    # The marker was there before: never removed with the entries written here.
    assert "marker no" in (index_dir / RECORD_TYPE / "my_robot").read_text()
    monkeypatch.undo()
    write_index(prefix, [], project=None)
    assert (index_dir / "packages" / "my_robot").exists()
    assert not (index_dir / "rclcpp_components" / "my_robot").exists()


def test_the_containers_own_package_goes_only_into_the_prefix_it_is_installed_in(tmp_path: Path) -> None:
    home = installed_prefix("lifecycle-container")
    assert home == Path(sys.prefix).resolve()
    # What an earlier version wrote into a plugin's prefix goes again.
    index_dir = tmp_path / "share" / "ament_index" / "resource_index"
    (index_dir / RECORD_TYPE).mkdir(parents=True)
    (index_dir / RECORD_TYPE / PROJECT_PACKAGE).write_text(
        "distribution lifecycle-container\nmarker yes\nexecutables component_container\n"
    )
    for path in (index_dir / "packages" / PROJECT_PACKAGE, tmp_path / "lib" / PROJECT_PACKAGE / "component_container"):
        path.parent.mkdir(parents=True, exist_ok=True)
        path.touch()

    refused = write_index(tmp_path, [], strict=True)
    assert refused.skipped == [(PROJECT_PACKAGE, f"lifecycle-container is installed in {home}, not in {tmp_path} "
                                                 f"(container index --prefix {home})")]
    assert refused.changed == []

    report = write_index(tmp_path, [])
    assert (report.registered, report.removed) == ({}, [PROJECT_PACKAGE])
    assert files_under(tmp_path) == {}


def test_a_refused_name_leaves_the_prefix_untouched(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    types = installed_plugin(tmp_path, monkeypatch, "my-robot")
    foreign = tmp_path / "share" / "ament_index" / "resource_index" / "packages" / "test_nodes"
    foreign.parent.mkdir(parents=True)
    foreign.touch()
    site = install_test_plugin(tmp_path / "elsewhere", distribution="test-nodes", module="tests.fault_plugin")
    monkeypatch.syspath_prepend(str(site))
    types += [t for t in PluginRegistry().types.values() if t.distribution == "test-nodes"]
    assert types and {t.package for t in types} == {"my_robot", "test_nodes"}
    before = files_under(tmp_path)

    report = write_index(tmp_path, types, project=None, prune=False, strict=True)

    assert [package for package, _ in report.skipped] == ["test_nodes"]
    assert (report.registered, report.changed, files_under(tmp_path)) == ({}, [], before)


# Indexes in child processes.
@pytest.mark.slow
def test_index_of_named_distributions_registers_only_them_in_their_prefix(tmp_path: Path) -> None:
    # Issue 45: `container index --prefix install/my_robot --distribution my_robot`
    # after colcon built an ament_python plugin (its marker and metadata in its
    # prefix) refused my_robot and wrote lifecycle_container's entries and four
    # executables there instead.
    prefix = tmp_path / "install" / "my_robot"
    index_dir = prefix / "share" / "ament_index" / "resource_index"
    (index_dir / "packages").mkdir(parents=True)
    (index_dir / "packages" / "my_robot").touch()
    site = prefix / "lib" / f"python{sys.version_info.major}.{sys.version_info.minor}" / "site-packages"
    install_test_plugin(site, distribution="my_robot")
    elsewhere = install_test_plugin(tmp_path / "site", distribution="test-nodes", module="tests.fault_plugin")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(site), str(elsewhere), str(IMPORT_ROOT)]))

    def index(*names: str) -> subprocess.CompletedProcess[str]:
        options = [option for name in names for option in ("--distribution", name)]
        return subprocess.run(
            [sys.executable, "-m", "container", "index", "--prefix", str(prefix), *options],
            capture_output=True, text=True, timeout=60, env=env, cwd=REPO,
        )

    done = index("my_robot")
    assert (done.returncode, done.stderr) == (0, ""), done.stderr
    assert done.stdout == f"ament index of {prefix}: 2 file(s) changed\n  my_robot: 4 node type(s)\n"
    assert sorted(files_under(prefix / "share")) == [
        "ament_index/resource_index/lifecycle_container_plugins/my_robot",
        "ament_index/resource_index/packages/my_robot",
        "ament_index/resource_index/rclcpp_components/my_robot",
    ]
    assert sorted(path.name for path in prefix.iterdir()) == ["lib", "share"]
    assert [path.name for path in (prefix / "lib").iterdir()] == [site.parent.name]
    env_prefix = dict(os.environ, AMENT_PREFIX_PATH=str(prefix))
    found = subprocess.run(
        [sys.executable, "-c", "from ament_index_python import get_package_prefix as p, get_resource as r;"
         "print(p('my_robot')); print(r('rclcpp_components', 'my_robot')[0], end='')"],
        capture_output=True, text=True, env=env_prefix, timeout=60,
    )
    assert found.stdout.splitlines()[0] == str(prefix), found.stderr
    assert "my_robot::Busy;tests.component_support:Busy" in found.stdout.splitlines()

    # Refused before anything is written: the container's own package (installed
    # in the test environment), a plugin with another's marker, an unknown name.
    before = files_under(prefix)
    refused = index("my_robot", "lifecycle-container")
    home = installed_prefix("lifecycle-container")
    assert (refused.returncode, refused.stderr) == (1, (
        f"container index: lifecycle_container not registered: lifecycle-container is installed in {home}, "
        f"not in {prefix} (container index --prefix {home})\n"
        f"container index: nothing written in {prefix}\n"
    ))
    (index_dir / "packages" / "test_nodes").touch()
    before = files_under(prefix)
    refused = index("test-nodes")
    assert refused.returncode == 1
    assert f"a ROS package named 'test_nodes' is already installed in {prefix}" in refused.stderr
    assert files_under(prefix) == before
    unknown = index("no-such-plugin")
    assert (unknown.returncode, unknown.stderr) == (1, "container index: no node types from no_such_plugin\n")


# -- a launch file's ComposableNodeContainer, as launch_ros runs it ---------------------------------


@pytest.fixture
def launched(
    ament_prefix_path: str, tmp_path: Path
) -> Iterator[LoggedProcess]:
    """ComposableNodeContainer(package='lifecycle_container', executable='component_container',
    name='my_container', namespace='launch_ns', parameters=[{'use_sim_time': True}])."""
    executable = executable_in_package(PROJECT_PACKAGE, "component_container")
    params = launch_params_file(tmp_path, "/launch_ns/my_container", {"use_sim_time": True})
    process = LoggedProcess(
        container_command(executable, name="my_container", namespace="/launch_ns", params_file=params)
    )
    try:
        process.wait_for_line("Container '/launch_ns/my_container' ready with 0 node(s)")
        yield process
    finally:
        process.close()


# ros2 launch in a child process.
@pytest.mark.slow
def test_a_launch_files_container_comes_up_named_and_loads_its_composable_nodes(
    launched: LoggedProcess, client_node: Node, executor: AsyncioExecutor, tmp_path: Path
) -> None:
    client = ContainerClient(client_node, executor, "/launch_ns/my_container")
    get: Client[Any, Any] = client_node.create_client(GetParameters, "/launch_ns/my_container/get_parameters")
    assert get.wait_for_service(timeout_sec=20.0)
    values = client.call(get, GetParameters.Request(names=["use_sim_time"])).values
    assert values[0].bool_value is True, "the --params-file entry for the container's full name was not applied"

    talker = client.load(composable_node_request(
        package="lifecycle_container", plugin="lifecycle_container::Talker", name="talker", namespace="demo",
        remappings=[("chatter", "/launch_chatter")],
        parameters={"rate": 20.0, "message": "From launch", "unused": {"nested": 1}},
        extra_arguments={"use_intra_process_comms": True, "autostart": True},
    ))
    assert (talker.success, talker.full_node_name) == (True, "/demo/talker"), talker.error_message
    # On success the answer holds the warnings the load caused (launch_ros reads it only on failure).
    assert talker.error_message == (
        "[WARN] [demo.talker]: Unknown parameter 'unused.nested' ignored: this node does not read it"
    )
    # A ComposableLifecycleNode(autostart=True) of launch_ros 0.26.7+: loaded, then
    # LifecycleTransition calls change_state (configure, activate).
    listener = client.load(composable_node_request(
        package="lifecycle_container", plugin="lifecycle_container::Listener", name="listener", namespace="/demo",
        remappings=[("chatter", "/launch_chatter")],
    ))
    assert (listener.success, listener.full_node_name) == (True, "/demo/listener"), listener.error_message
    change: Client[Any, Any] = client_node.create_client(ChangeState, "/demo/listener/change_state")
    assert change.wait_for_service(timeout_sec=20.0)
    for transition in (Transition.TRANSITION_CONFIGURE, Transition.TRANSITION_ACTIVATE):
        request = ChangeState.Request()
        request.transition.id = transition
        assert client.call(change, request).success
    launched.wait_for_line("I heard: [From launch:")
    assert client.list() == [(1, "/demo/talker"), (2, "/demo/listener")]
    state: Client[Any, Any] = client_node.create_client(GetState, "/demo/talker/get_state")
    assert state.wait_for_service(timeout_sec=20.0)
    assert client.call(state, GetState.Request()).current_state.label == "active"
    assert launched.stop() == 0
    assert "threads left behind" not in launched.output(last=1000)


# ros2 launch with a lifecycle manager, in child processes.
@pytest.mark.slow
def test_nav2_style_lifecycle_manager_brings_up_the_launched_nodes(
    launched: LoggedProcess, client_node: Node, executor: AsyncioExecutor, tmp_path: Path
) -> None:
    """Node(package='lifecycle_container', executable='lifecycle_manager', name='lifecycle_manager_test',
    parameters=[{'autostart': True, 'node_names': ['/demo/talker']}]), as a Nav2 launch file starts it."""
    client = ContainerClient(client_node, executor, "/launch_ns/my_container")
    loaded = client.load(composable_node_request(
        package="lifecycle_container", plugin="lifecycle_container::Talker", name="talker", namespace="/demo",
    ))
    assert loaded.success, loaded.error_message
    executable = executable_in_package(PROJECT_PACKAGE, "lifecycle_manager")
    params = launch_params_file(
        tmp_path, "/lifecycle_manager_test", {"autostart": True, "node_names": ["/demo/talker"], "bond_timeout": 0.0}
    )
    manager = LoggedProcess(
        [executable, "--ros-args", "-r", "__node:=lifecycle_manager_test", "--params-file", str(params)]
    )
    try:
        line = manager.wait_for_line("Managed nodes are active", timeout=30)
        assert "[lifecycle_manager_test]" in line
        state: Client[Any, Any] = client_node.create_client(GetState, "/demo/talker/get_state")
        assert state.wait_for_service(timeout_sec=20.0)
        assert client.call(state, GetState.Request()).current_state.label == "active"
        assert manager.stop() == 0
    finally:
        manager.close()
