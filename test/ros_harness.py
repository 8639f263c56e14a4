"""Helpers for tests that talk to a real sysid_node over DDS."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
from rcl_interfaces.srv import SetParameters
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from std_srvs.srv import Trigger

from spm_sysid.apps.pipeline import stop_process
from spm_sysid.ros.sysid_node import LATCHED

ROOT = Path(__file__).resolve().parents[1]


def start_node(env, *params, params_file=None, log=None, schema_defaults=False,
               open_files=None):
    """Start sysid_node as its own process.

    Diagnostics come every 0.2 s unless a test sets the period or asks for the
    schema's defaults (the harness waits on them), so a test does not idle a
    second per wait. ``open_files``: the process's limit of file descriptors
    (``ulimit -n``), as a small robot computer or a container may set it.
    """
    args = [sys.executable, "-m", "spm_sysid.ros.sysid_node", "--ros-args"]
    if (params_file is None and not schema_defaults
            and not any(p.startswith("diagnostics_period:=") for p in params)):
        params = ("diagnostics_period:=0.2", *params)
    for p in params:
        args += ["-p", p]
    if params_file:
        args += ["--params-file", str(params_file)]
    def limit():
        import resource

        resource.setrlimit(resource.RLIMIT_NOFILE, (open_files, open_files))

    return subprocess.Popen(args, env=env, stdout=log or subprocess.DEVNULL,
                            stderr=subprocess.STDOUT, cwd=ROOT,
                            preexec_fn=limit if open_files else None)


stop = stop_process


class Harness:
    """An rclpy context and node in the test process, on the test's domain."""

    def __init__(self, env):
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=int(env["ROS_DOMAIN_ID"]))
        os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
        self.node = Node("test_harness", context=self.context)
        self._executor = SingleThreadedExecutor(context=self.context)
        self._executor.add_node(self.node)
        self.diag: list[DiagnosticArray] = []
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self.diag.append, 50)
        self._action_clients: list = []

    def action_client(self, action_type, name: str, **options):
        """An action client on the harness's node, destroyed by :meth:`close`.

        ``destroy_node`` leaves an action client alive (rclpy destroys only topics,
        services, timers and guard conditions); one destroyed later by the garbage
        collector, after its context's shutdown and in some other test, is how a
        client library can crash a process, so each is destroyed before the node.
        """
        from rclpy.action import ActionClient

        client = ActionClient(self.node, action_type, name, **options)
        self._action_clients.append(client)
        return client

    def close(self):
        for client in self._action_clients:
            client.destroy()
        self._action_clients.clear()
        self._executor.shutdown()
        self.node.destroy_node()
        rclpy.shutdown(context=self.context)

    def _spin_once(self, timeout):
        self._executor.spin_once(timeout_sec=timeout)

    def spin_until(self, predicate, timeout):
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if predicate():
                return True
            self._spin_once(0.05)
        return predicate()

    def statuses(self) -> dict:
        """name suffix -> (level, message, values) of the newest diagnostics message."""
        if not self.diag:
            return {}
        out = {}
        for st in self.diag[-1].status:
            level = st.level[0] if isinstance(st.level, bytes) else int(st.level)
            out[st.name.split(": ", 1)[-1]] = (level, st.message,
                                               {k.key: k.value for k in st.values})
        return out

    def buffer(self) -> dict:
        return self.statuses().get("buffer", (None, None, {}))[2]

    def wait_buffer(self, predicate, timeout=30.0) -> dict:
        self.diag.clear()
        self.spin_until(lambda: bool(self.buffer()) and predicate(self.buffer()), timeout)
        return self.buffer()

    def wait_ready(self, timeout=60.0):
        kv = self.wait_buffer(lambda kv: kv.get("worker_ready") == "True", timeout)
        assert kv.get("worker_ready") == "True", "sysid_node did not come up"

    def call(self, service, timeout=120.0):
        client = self.node.create_client(Trigger, service)
        try:
            assert client.wait_for_service(timeout_sec=30.0), f"{service} not available"
            future = client.call_async(Trigger.Request())
            self.spin_until(future.done, timeout)
            assert future.done(), f"no answer from {service}"
            return future.result()
        finally:
            self.node.destroy_client(client)

    def call_async(self, service):
        client = self.node.create_client(Trigger, service)
        assert client.wait_for_service(timeout_sec=30.0)
        return client.call_async(Trigger.Request())

    def set_parameters(self, node_name, **values):
        client = self.node.create_client(SetParameters, f"{node_name}/set_parameters")
        try:
            assert client.wait_for_service(timeout_sec=30.0)
            req = SetParameters.Request()
            for name, value in values.items():
                pv = ParameterValue()
                if isinstance(value, bool):
                    pv.type, pv.bool_value = ParameterType.PARAMETER_BOOL, value
                elif isinstance(value, int):
                    pv.type, pv.integer_value = ParameterType.PARAMETER_INTEGER, value
                elif isinstance(value, float):
                    pv.type, pv.double_value = ParameterType.PARAMETER_DOUBLE, value
                else:
                    pv.type, pv.string_value = ParameterType.PARAMETER_STRING, value
                req.parameters.append(Parameter(name=name, value=pv))
            future = client.call_async(req)
            self.spin_until(future.done, 30)
            return future.result().results
        finally:
            self.node.destroy_client(client)

    def latched(self, msg_type, topic, timeout=10.0):
        """Subscribe now (late) with the latched QoS; the last message or None."""
        got = []
        sub = self.node.create_subscription(msg_type, topic, got.append, LATCHED)
        try:
            self.spin_until(lambda: bool(got), timeout)
            return got[-1] if got else None
        finally:
            self.node.destroy_subscription(sub)


def publisher(env, *args):
    """Start the signal publisher; returns the process (JSON lines on stdout)."""
    return subprocess.Popen([sys.executable, "-m", "spm_sysid.ros.signal_publisher",
                             *map(str, args)],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            cwd=ROOT)


def finish_publisher(proc, timeout=120):
    out, err = proc.communicate(timeout=timeout)
    assert proc.returncode == 0, err
    return json.loads(out.strip().splitlines()[-1])


class IdentifyClient:
    """An action client of ``/spm_sysid/identify`` on a harness's node."""

    def __init__(self, harness: Harness, name: str = "/spm_sysid/identify"):
        from spm_sysid_interfaces.action import Identify

        self.harness, self.Identify = harness, Identify
        self.client = harness.action_client(Identify, name)
        assert self.client.wait_for_server(timeout_sec=30.0), f"no action server {name}"

    def send(self, feedback: list | None = None, bag_path: str = "", **overrides):
        """Send a goal; the accepted goal handle (overrides as setting=text)."""
        goal = self.Identify.Goal(setting_names=list(overrides),
                                  setting_values=[str(v) for v in overrides.values()],
                                  bag_path=str(bag_path))
        cb = None if feedback is None else (lambda m: feedback.append(m.feedback))
        future = self.client.send_goal_async(goal, feedback_callback=cb)
        assert self.harness.spin_until(future.done, 30), "goal not answered"
        handle = future.result()
        assert handle.accepted
        return handle

    def result(self, handle, timeout: float = 120.0):
        """(status, result) of a goal."""
        future = handle.get_result_async()
        assert self.harness.spin_until(future.done, timeout), "no result"
        return future.result().status, future.result().result

    def get_model(self, name: str = "/spm_sysid/get_model"):
        from spm_sysid_interfaces.srv import GetModel

        client = self.harness.node.create_client(GetModel, name)
        try:
            assert client.wait_for_service(timeout_sec=30.0)
            future = client.call_async(GetModel.Request())
            assert self.harness.spin_until(future.done, 30)
            return future.result()
        finally:
            self.harness.node.destroy_client(client)


def play_bag(env, bag, rate=10.0):
    """Replay a bag with bag_player (waits for the node to subscribe); asserts it worked."""
    r = subprocess.run([sys.executable, "-m", "spm_sysid.ros.bag_player", "--ros-args",
                        "-p", f"bag:={bag}", "-p", f"rate:={rate}"],
                       capture_output=True, text=True, env=env, timeout=120, cwd=ROOT)
    assert r.returncode == 0, r.stderr
