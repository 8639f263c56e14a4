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

__all__ = ["LATCHED", "RELIABLE_KEEP_ALL", "REQUESTS", "CallbackErrors", "asks_for_help",
           "message_class", "run_node"]

#: Latched: reliable + transient-local, depth 1; a late subscriber gets the last message.
LATCHED = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                     reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)

#: Reliable, keep-all, volatile: a burst waits in the queue instead of being dropped.
RELIABLE_KEEP_ALL = QoSProfile(history=HistoryPolicy.KEEP_ALL,
                               reliability=ReliabilityPolicy.RELIABLE,
                               durability=DurabilityPolicy.VOLATILE)


#: Services and the action's goal, cancel and result requests: every request is
#: kept until the executor takes it (rclpy's default keeps the last 10, so a burst of
#: more simultaneous requests lost some, and their clients waited forever).
REQUESTS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000,
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


#: Callback errors logged with their traceback; later ones are counted only.
LOGGED_CALLBACK_ERRORS = 10


class CallbackErrors:
    """Callbacks that raised while a node spun: counted (``count``), the first ones logged.

    A node that reports them (``/diagnostics``) owns one as ``callback_errors``;
    :func:`run_node` counts into it.
    """

    def __init__(self, logger) -> None:
        self.logger, self.count = logger, 0

    def __call__(self, exc: BaseException) -> None:
        import traceback

        self.count += 1
        if self.count <= LOGGED_CALLBACK_ERRORS:
            where = traceback.extract_tb(exc.__traceback__)[-1]
            self.logger.error(
                f"a callback raised {type(exc).__name__}: {exc} ({where.filename}:"
                f"{where.lineno}); the node goes on (callback_errors {self.count} in "
                "/diagnostics)")


def _spin_resilient(executor, errors: CallbackErrors) -> None:
    """Spin until shut down; a callback that raises is logged and counted, not fatal."""
    while rclpy.ok():
        try:
            executor.spin_once(timeout_sec=0.5)
        except (KeyboardInterrupt, ExternalShutdownException):
            raise
        except Exception as exc:  # noqa: BLE001 - one bad callback must not stop the node
            if not rclpy.ok():  # SIGINT/SIGTERM shut the context down mid-wait
                return
            errors(exc)


def _spin_once(executor, timeout_sec: float) -> None:
    """One wait of the executor; nothing when the context was shut down meanwhile.

    SIGINT or SIGTERM may shut the context down between the loop's ``rclpy.ok()``
    and the wait, which then raises ``RCLError`` (the context is not valid): an
    interruption, not a failure (a loaded CI run's bag_player printed a traceback).
    """
    from rclpy._rclpy_pybind11 import RCLError

    try:
        executor.spin_once(timeout_sec=timeout_sec)
    except RCLError:
        if rclpy.ok():
            raise


def asks_for_help(args: list[str] | None) -> bool:
    """``-h`` or ``--help`` before any ``--ros-args`` (ROS's own arguments come after it)."""
    argv = sys.argv[1:] if args is None else list(args)
    before = argv[:argv.index("--ros-args")] if "--ros-args" in argv else argv
    return any(a in ("-h", "--help") for a in before)


def _init(args: list[str] | None) -> bool:
    """``rclpy.init``; False (with one error line) when ROS cannot read the arguments."""
    from rclpy._rclpy_pybind11 import RCLError

    try:
        rclpy.init(args=args)
    except RCLError as exc:  # e.g. -p dashboard_host:=:: (YAML reads "::" otherwise)
        why = str(exc).split("Error:", 1)[-1].split(", at ")[0].strip()
        print(f"error: ROS cannot read the command line's arguments ({why}); a value YAML "
              "reads as something else must be quoted, e.g. -p 'dashboard_host:=\"::\"'",
              file=sys.stderr)
        return False
    return True


def _spin(executor: SingleThreadedExecutor, node: Node,
          until: Callable[[Node], bool] | None) -> None:
    """Until ``until(node)`` or, without it, until shut down, callbacks' errors counted."""
    if until is None:
        errors_of = getattr(node, "callback_errors", None)
        _spin_resilient(executor, errors_of if isinstance(errors_of, CallbackErrors)
                        else CallbackErrors(node.get_logger()))
        return
    while rclpy.ok() and not until(node):
        _spin_once(executor, 0.1)


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
        Spin until ``until(node)`` is true (a tool that ends; an exception of
        ``errors`` in a callback ends it with one ``error:`` line). Default: spin
        until shut down (a node that runs next to a robot): a callback that
        raises is logged, counted in the node's own :class:`CallbackErrors`
        (``node.callback_errors``, when it has one) and the node goes on.
    errors : tuple of exception types
        What ``build`` may raise for a user's mistake (bad parameters).
    finish : callable, optional
        ``finish(node, interrupted)`` returns the exit status (and may print).
        Without it: 0, or 130 when interrupted (SIGINT/SIGTERM).
    args : list of str, optional
        Command-line arguments for ``rclpy.init``.
    """
    quiet = _quiet_interrupts()
    if not _init(args):
        _restore(quiet)
        return 2
    executor = SingleThreadedExecutor()
    node = None
    interrupted = False
    status = 0
    try:
        node = build()
        executor.add_node(node)
        _spin(executor, node, until)
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
        _restore(quiet)
    return status


def _quiet_interrupts():
    """SIGINT without a KeyboardInterrupt: rclpy's handler shuts the context down.

    Set before ``rclpy.init``, whose handler calls the one before it: Python's
    default raises KeyboardInterrupt wherever the interpreter is, even inside
    a finaliser at shutdown (``Exception ignored in: Future.__del__ ...
    KeyboardInterrupt``, a traceback in the node's log). The spin loops end on
    ``rclpy.ok()`` instead. The handler before, to restore (None off the main
    thread, where none can be set).
    """
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        return None
    return signal.signal(signal.SIGINT, lambda signum, frame: None)


def _restore(previous) -> None:
    """The SIGINT handler :func:`_quiet_interrupts` replaced, back."""
    import signal

    if previous is not None:
        signal.signal(signal.SIGINT, previous)
