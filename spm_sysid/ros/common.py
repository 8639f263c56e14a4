"""What the ROS executables share: QoS profiles, message classes, the main loop.

Each executable (``sysid_node``, ``bag_player``, ``signal_publisher``) imports
this module and the core, never another executable.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from ..core.errors import BagError

__all__ = ["LATCHED", "RELIABLE_KEEP_ALL", "message_class", "run_node"]

#: Latched: reliable + transient-local, depth 1; a late subscriber gets the last message.
LATCHED = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                     reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)

#: Reliable, keep-all, volatile: a burst waits in the queue instead of being dropped.
RELIABLE_KEEP_ALL = QoSProfile(history=HistoryPolicy.KEEP_ALL,
                               reliability=ReliabilityPolicy.RELIABLE,
                               durability=DurabilityPolicy.VOLATILE)


def message_class(msgtype: str):
    """The rclpy message class for a type name such as ``geometry_msgs/msg/Twist``."""
    try:
        package, kind, name = msgtype.split("/")
        return getattr(importlib.import_module(f"{package}.{kind}"), name)
    except (ImportError, AttributeError, ValueError):
        raise BagError(f"message type {msgtype} is not installed in this ROS environment") \
            from None


def run_node(build: Callable[[], Node], *, until: Callable[[Node], bool] | None = None,
             errors: tuple[type[BaseException], ...] = (ValueError,),
             finish: Callable[[Node, bool], int] | None = None,
             args: list[str] | None = None) -> int:
    """The executables' main loop: init, build, spin, always clean up.

    Parameters
    ----------
    build : callable
        Makes the node; an exception of ``errors`` becomes one ``error:`` line and
        exit status 1.
    until : callable, optional
        Spin until ``until(node)`` is true (default: until shut down).
    errors : tuple of exception types
        What ``build`` may raise for a user's mistake (bad parameters).
    finish : callable, optional
        ``finish(node, interrupted)`` returns the exit status (and may print).
        Without it: 0, or 130 when interrupted (SIGINT/SIGTERM).
    args : list of str, optional
        Command-line arguments for ``rclpy.init``.
    """
    rclpy.init(args=args)
    executor = SingleThreadedExecutor()
    node = None
    interrupted = False
    status = 0
    try:
        node = build()
        executor.add_node(node)
        if until is None:
            executor.spin()
        else:
            while rclpy.ok() and not until(node):
                executor.spin_once(timeout_sec=0.1)
            interrupted = not rclpy.ok()  # SIGINT/SIGTERM shut the context down
    except errors as exc:
        print(f"error: {exc}", file=sys.stderr)
        status = 1
    except (KeyboardInterrupt, ExternalShutdownException):
        interrupted = True
    finally:
        if node is not None:
            close = getattr(node, "close", None)
            if close is not None:
                close()
            if status == 0:
                status = finish(node, interrupted) if finish else (130 if interrupted else 0)
            node.destroy_node()
        executor.shutdown(timeout_sec=1.0)
        if rclpy.ok():
            rclpy.shutdown()
    return status
