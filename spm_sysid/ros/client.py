"""A client of the node, for the command line, the pipeline and the benchmarks.

Plain functions over an rclpy node of the caller's: set parameters
(:func:`set_parameters`), call a Trigger service (:func:`call_trigger`), send
an ``Identify`` goal and wait for its result, Ctrl-C canceling it
(:func:`identify_goal`), read the latched model (:func:`wait_for_model`), watch
a status on ``/diagnostics`` (:func:`wait_for_buffer`). Requests and answers
keep a deep history (:data:`~spm_sysid.ros.common.REQUESTS`), so a burst is
never lost on this side; a wait longer than a moment says so on stderr.
"""

from __future__ import annotations

import json
import signal
import sys
import threading
import time
from contextlib import contextmanager

import rclpy
from rclpy.node import Node
from std_msgs.msg import String
from std_srvs.srv import Trigger

from .common import LATCHED, REQUESTS

__all__ = ["CANCEL_WAIT", "GoalOutcome", "call_trigger", "identify_goal", "set_parameters",
           "wait_for", "wait_for_buffer", "wait_for_model"]

#: Seconds to wait for a canceled goal's result after Ctrl-C.
CANCEL_WAIT = 10.0


#: Seconds of silence before saying that the node is being waited for.
SAY_WAITING = 3.0


def wait_for(ready, what: str, timeout: float) -> None:
    """Wait up to ``timeout`` s for ``ready(seconds)``; say so on stderr after a moment.

    With no node running, a user learns at once that the command waits, and
    for how long, instead of staring at a silent terminal. ``what`` names it
    (``service /spm_sysid/clear``).

    Raises
    ------
    TimeoutError
        Not there within ``timeout`` seconds.
    """
    first = min(timeout, SAY_WAITING)
    if ready(first):
        return
    name = what.split(" ", 1)[-1]
    if timeout > first:
        print(f"still waiting for {name} after {first:g} s (up to {timeout - first:.0f} s "
              "more; is sysid_node running, with the same ROS_DOMAIN_ID?) ...",
              file=sys.stderr, flush=True)
        if ready(timeout - first):
            return
    raise TimeoutError(f"{what} is not available (is sysid_node running, with the same "
                       "ROS_DOMAIN_ID?)")


def set_parameters(node: Node, target: str, timeout: float = 10.0, **values) -> None:
    """Set parameters of node ``target`` (e.g. ``/spm_sysid``) through its service.

    Raises
    ------
    RuntimeError
        A value was refused (the node's reason is in the message), or no answer.
    """
    from rcl_interfaces.srv import SetParameters
    from rclpy.parameter import Parameter

    client = node.create_client(SetParameters, f"{target}/set_parameters")
    try:
        if not client.wait_for_service(timeout_sec=timeout):
            raise RuntimeError(f"{target} offers no parameter service")
        req = SetParameters.Request(parameters=[Parameter(k, value=v).to_parameter_msg()
                                                for k, v in values.items()])
        future = client.call_async(req)
        rclpy.spin_until_future_complete(node, future, timeout_sec=timeout)
        if not future.done():
            raise RuntimeError(f"{target} did not answer set_parameters within {timeout:g} s")
        for name, result in zip(values, future.result().results):
            if not result.successful:
                raise RuntimeError(f"{target} refused {name}: {result.reason}")
    finally:
        node.destroy_client(client)


def call_trigger(node: Node, service: str, timeout: float = 300.0) -> tuple[bool, str]:
    """Call a ``std_srvs/srv/Trigger`` service; returns ``(success, message)``.

    Raises
    ------
    TimeoutError
        The service did not appear, or did not answer, within ``timeout`` seconds.
    """
    client = node.create_client(Trigger, service, qos_profile=REQUESTS)
    try:
        deadline = time.monotonic() + timeout
        wait_for(lambda t: client.wait_for_service(timeout_sec=t), f"service {service}",
                 min(timeout, 30.0))
        future = client.call_async(Trigger.Request())
        rclpy.spin_until_future_complete(node, future,
                                         timeout_sec=max(0.1, deadline - time.monotonic()))
        if not future.done():
            raise TimeoutError(f"no answer from {service} within {timeout:.0f} s")
        result = future.result()
        return bool(result.success), str(result.message)
    finally:
        node.destroy_client(client)


@contextmanager
def _interrupts():
    """An event set by Ctrl-C (SIGINT) inside the block, instead of a KeyboardInterrupt.

    A KeyboardInterrupt raised inside an rclpy callback or task (a feedback
    message being handled) can be swallowed by the executor, and the goal then
    runs on; a flag checked between spins is never lost. Outside the main
    thread no handler can be set: Ctrl-C stays a KeyboardInterrupt there.
    """
    flag = threading.Event()
    try:
        before = signal.signal(signal.SIGINT, lambda *_: flag.set())
    except ValueError:  # not the main thread
        before = None
    try:
        yield flag
    finally:
        if before is not None:
            signal.signal(signal.SIGINT, before)


class GoalOutcome:
    """How a goal ended: ``status`` (action_msgs GoalStatus), ``result`` (Identify.Result)."""

    def __init__(self, status: int, result, interrupted: bool = False) -> None:
        self.status, self.result, self.interrupted = status, result, interrupted


def identify_goal(node: Node, action: str, overrides: dict[str, str] | None = None,
                  bag_path: str = "", timeout: float = 300.0,
                  on_feedback=None) -> GoalOutcome:
    """Send an ``Identify`` goal and wait for its result.

    Ctrl-C (KeyboardInterrupt) while waiting cancels the goal and waits up to
    :data:`CANCEL_WAIT` seconds for the canceled result. ``overrides`` are
    settings as text (``{"criterion": "bic"}``), checked by the node.

    Raises
    ------
    TimeoutError
        No action server, no answer to the goal, or no result within ``timeout``.
    """
    from rclpy.action import ActionClient
    from spm_sysid_interfaces.action import Identify

    overrides = overrides or {}
    client = ActionClient(node, Identify, action, goal_service_qos_profile=REQUESTS,
                          result_service_qos_profile=REQUESTS,
                          cancel_service_qos_profile=REQUESTS)
    try:
        deadline = time.monotonic() + timeout
        wait_for(lambda t: client.wait_for_server(timeout_sec=t), f"action {action}",
                 min(timeout, 30.0))
        goal = Identify.Goal(setting_names=list(overrides),
                             setting_values=[str(v) for v in overrides.values()],
                             bag_path=bag_path)
        sent = client.send_goal_async(
            goal, feedback_callback=None if on_feedback is None
            else (lambda m: on_feedback(m.feedback)))
        rclpy.spin_until_future_complete(node, sent, timeout_sec=min(timeout, 30.0))
        if not sent.done() or not sent.result().accepted:
            raise TimeoutError(f"{action} did not accept the goal")
        handle = sent.result()
        result = handle.get_result_async()
        with _interrupts() as interrupted:
            try:
                while not result.done() and not interrupted.is_set() and \
                        time.monotonic() < deadline:
                    rclpy.spin_once(node, timeout_sec=0.1)
            except KeyboardInterrupt:  # where no handler could be set (not the main thread)
                interrupted.set()
        interrupted = interrupted.is_set()
        if interrupted:
            cancel = handle.cancel_goal_async()
            rclpy.spin_until_future_complete(node, cancel, timeout_sec=CANCEL_WAIT)
            rclpy.spin_until_future_complete(node, result, timeout_sec=CANCEL_WAIT)
        if not result.done():
            if not interrupted:
                handle.cancel_goal_async()  # do not leave a search running for nobody
                rclpy.spin_once(node, timeout_sec=0.5)
            raise TimeoutError(f"no result from {action} within "
                               f"{CANCEL_WAIT if interrupted else timeout:.0f} s")
        return GoalOutcome(result.result().status, result.result().result, interrupted)
    finally:
        client.destroy()


def wait_for_model(node: Node, topic: str, timeout: float = 10.0) -> dict | None:
    """The latest model document on a latched ``~/model`` topic, or None."""
    got: list[dict] = []
    sub = node.create_subscription(String, topic, lambda m: got.append(json.loads(m.data)),
                                   LATCHED)
    try:
        deadline = time.monotonic() + timeout
        while not got and time.monotonic() < deadline:
            rclpy.spin_once(node, timeout_sec=0.1)
        return got[-1] if got else None
    finally:
        node.destroy_subscription(sub)


def wait_for_buffer(node, done, timeout: float, status: str = "buffer") -> dict:
    """Watch a sysid node status on /diagnostics (``buffer``) until ``done(values)``.

    Returns the last key/value pairs seen (empty if none arrived).
    """
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray

    seen: dict = {}

    def on_diag(msg):
        for st in msg.status:
            if st.name.endswith(": " + status):
                seen.clear()
                seen.update({k.key: k.value for k in st.values})

    sub = node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, 10)
    deadline = time.monotonic() + timeout
    try:
        while time.monotonic() < deadline and not (seen and done(seen)):
            rclpy.spin_once(node, timeout_sec=0.1)
    finally:
        node.destroy_subscription(sub)
    return seen
