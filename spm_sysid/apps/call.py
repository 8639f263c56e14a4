"""Calling the node's services without the ``ros2`` command line.

``spm-sysid call identify`` / ``spm-sysid call clear`` use :func:`call_trigger`;
another rclpy node can do the same with its own client (see
``examples/identify_from_node.py``).
"""

from __future__ import annotations

import json
import sys
import time

import rclpy
from rclpy.node import Node
from std_msgs.msg import String
from std_srvs.srv import Trigger

from ..ros.common import LATCHED

__all__ = ["call_trigger", "main", "set_parameters", "wait_for_model"]


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
    client = node.create_client(Trigger, service)
    try:
        deadline = time.monotonic() + timeout
        if not client.wait_for_service(timeout_sec=min(timeout, 30.0)):
            raise TimeoutError(f"service {service} is not available (is sysid_node running, "
                               "with the same ROS_DOMAIN_ID?)")
        future = client.call_async(Trigger.Request())
        rclpy.spin_until_future_complete(node, future,
                                         timeout_sec=max(0.1, deadline - time.monotonic()))
        if not future.done():
            raise TimeoutError(f"no answer from {service} within {timeout:.0f} s")
        result = future.result()
        return bool(result.success), str(result.message)
    finally:
        node.destroy_client(client)


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


def main(action: str, node_name: str = "/spm_sysid", timeout: float = 300.0,
         show_model: bool = False) -> int:
    """Entry of ``spm-sysid call``; prints the answer, returns an exit status."""
    from rclpy.exceptions import NameValidationException
    from rclpy.validate_full_topic_name import validate_full_topic_name

    name = "/" + node_name.strip("/")
    try:
        validate_full_topic_name(f"{name}/{action}", is_service=True)
    except NameValidationException as exc:
        reason = str(exc).splitlines()[0].split(": ", 1)[-1].rstrip(":")
        print(f"error: --node {node_name!r} is not a valid ROS node name ({reason})",
              file=sys.stderr)
        return 2
    node_name = name
    rclpy.init()
    node = Node("spm_sysid_call")
    try:
        ok, message = call_trigger(node, f"{node_name.rstrip('/')}/{action}", timeout)
        if ok:
            print("success: " + message)
        else:
            print("refused: " + message, file=sys.stderr)
        if ok and action == "identify" and show_model:
            doc = wait_for_model(node, f"{node_name.rstrip('/')}/model")
            if doc is not None:
                print(json.dumps(doc, indent=2))
        return 0 if ok else 1
    except TimeoutError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    finally:
        node.destroy_node()
        rclpy.shutdown()
