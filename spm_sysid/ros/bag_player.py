"""``bag_player``: replay a rosbag2 bag's topics with their recorded timing.

A small stand-in for ``ros2 bag play`` (rosbag2 is not installable here): it
reads the bag with rosbags and publishes each message's recorded CDR bytes
unchanged, at ``recorded time / rate``.

Parameters (``--ros-args -p name:=value``):

``bag`` (string, required)  bag directory or ``.mcap`` file
``rate`` (double, 1.0)  playback speed factor (10.0 = ten times faster)
``start_delay`` (double, 0.0)  seconds to wait before the first message
``loop`` (bool, false)  start again at the end, until stopped
``topics`` (string[], all)  only these topics
``remap`` (string[], none)  ``from:=to`` pairs renaming published topics
``qos_depth`` (int, 1000)  keep-last depth of the reliable, volatile publishers;
    a default subscriber (reliable, volatile) matches them
``wait_for_subscribers`` (int, 0)  wait until each topic has this many matched
    subscribers before playing (at most ``wait_timeout`` seconds)
``wait_timeout`` (double, 10.0)
``settle_time`` (double, 1.0)  seconds to wait after the subscribers matched:
    discovery completes on the subscriber's side a little after the publisher
    sees it, and a reliable, volatile subscriber misses what was sent before

It logs how many messages it published per topic and exits with status 0 at
the end (or keeps looping); a bag it cannot read ends it with status 1 and one
error line.
"""

from __future__ import annotations

import importlib
import sys
import threading
import time
from collections import Counter
from pathlib import Path

import rclpy
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from ..core.bagio import BagError, open_bag

__all__ = ["BagPlayer", "main", "message_class"]


def message_class(msgtype: str):
    """The rclpy message class for a type name such as ``geometry_msgs/msg/Twist``."""
    package, kind, name = msgtype.split("/")
    try:
        return getattr(importlib.import_module(f"{package}.{kind}"), name)
    except (ImportError, AttributeError):
        raise BagError(f"message type {msgtype} is not installed in this ROS environment") \
            from None


class BagPlayer(Node):
    """Publishes a bag's messages on their topics with the recorded timing."""

    def __init__(self) -> None:
        super().__init__("bag_player")
        self.declare_parameter("bag", "", ParameterDescriptor(
            description="bag directory or .mcap file", read_only=True))
        self.declare_parameter("rate", 1.0, ParameterDescriptor(
            description="playback speed factor (> 0)", read_only=True))
        self.declare_parameter("start_delay", 0.0, ParameterDescriptor(
            description="seconds before the first message", read_only=True))
        self.declare_parameter("loop", False, ParameterDescriptor(
            description="replay from the start at the end", read_only=True))
        self.declare_parameter("topics", [""], ParameterDescriptor(
            description="topics to play (empty: all)", read_only=True))
        self.declare_parameter("remap", [""], ParameterDescriptor(
            description="from:=to topic renames", read_only=True))
        self.declare_parameter("qos_depth", 1000, ParameterDescriptor(
            description="keep-last depth of the publishers", read_only=True))
        self.declare_parameter("wait_for_subscribers", 0, ParameterDescriptor(
            description="matched subscribers per topic before playing", read_only=True))
        self.declare_parameter("wait_timeout", 10.0, ParameterDescriptor(
            description="longest wait for subscribers, seconds", read_only=True))
        self.declare_parameter("settle_time", 1.0, ParameterDescriptor(
            description="seconds to wait after subscribers matched", read_only=True))

        p = {name: self.get_parameter(name).value for name in (
            "bag", "rate", "start_delay", "loop", "topics", "remap", "qos_depth",
            "wait_for_subscribers", "wait_timeout", "settle_time")}
        if not p["bag"]:
            raise BagError("parameter 'bag' is required (--ros-args -p bag:=PATH)")
        if not p["rate"] > 0:
            raise BagError(f"parameter 'rate' must be > 0, got {p['rate']}")
        self.bag = Path(p["bag"])
        self.rate = float(p["rate"])
        self.start_delay = max(0.0, float(p["start_delay"]))
        self.loop = bool(p["loop"])
        self.wait_for = int(p["wait_for_subscribers"])
        self.wait_timeout = float(p["wait_timeout"])
        self.settle_time = max(0.0, float(p["settle_time"]))
        selected = [t for t in p["topics"] if t]
        remap = {}
        for item in (r for r in p["remap"] if r):
            src, sep, dst = item.partition(":=")
            if not sep or not src or not dst:
                raise BagError(f"remap entry {item!r} must look like from:=to")
            remap[src] = dst

        reader = open_bag(self.bag)  # fails early, with a clear message
        try:
            topics = {c.topic: c.msgtype for c in reader.connections}
        finally:
            reader.close()
        missing = [t for t in selected if t not in topics]
        if missing:
            raise BagError(f"{self.bag} has no topic {', '.join(missing)}; it has: "
                           f"{', '.join(sorted(topics))}")
        self.topics = {t: m for t, m in topics.items() if not selected or t in selected}
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=int(p["qos_depth"]),
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE)
        self.publishers_by_topic = {
            t: self.create_publisher(message_class(m), remap.get(t, t), qos)
            for t, m in self.topics.items()
        }
        self.published: Counter[str] = Counter()
        self.finished = threading.Event()
        self.error: str | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._play, name="bag-playback", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Ask the playback thread to end."""
        self._stop.set()

    def _wait_for_subscribers(self) -> None:
        deadline = time.monotonic() + self.wait_timeout
        while not self._stop.is_set() and time.monotonic() < deadline:
            counts = [pub.get_subscription_count() for pub in self.publishers_by_topic.values()]
            if min(counts, default=0) >= self.wait_for:
                self._stop.wait(self.settle_time)
                return
            time.sleep(0.02)
        self.get_logger().warning(
            f"went on after {self.wait_timeout:.1f} s without {self.wait_for} subscriber(s) "
            "on every topic")

    def _play(self) -> None:
        try:
            if self.wait_for > 0:
                self._wait_for_subscribers()
            if self.start_delay:
                self._stop.wait(self.start_delay)
            self.get_logger().info(
                f"playing {self.bag} at {self.rate:g}x: {', '.join(sorted(self.topics))}")
            while not self._stop.is_set():
                self._play_once()
                if not self.loop:
                    break
            summary = ", ".join(f"{t}: {n}" for t, n in sorted(self.published.items()))
            self.get_logger().info(f"published {sum(self.published.values())} messages "
                                   f"({summary or 'none'})")
        except Exception as exc:  # reported, and main() exits with status 1
            self.error = f"playback failed: {exc}"
        finally:
            self.finished.set()

    def _play_once(self) -> None:
        reader = open_bag(self.bag)
        try:
            conns = [c for c in reader.connections if c.topic in self.topics]
            start_wall = time.monotonic()
            first_ns = None
            for conn, t_ns, raw in reader.messages(connections=conns):
                if self._stop.is_set():
                    return
                if first_ns is None:
                    first_ns = t_ns
                due = start_wall + (t_ns - first_ns) / 1e9 / self.rate
                delay = due - time.monotonic()
                if delay > 0:
                    self._stop.wait(delay)
                self.publishers_by_topic[conn.topic].publish(bytes(raw))
                self.published[conn.topic] += 1
        finally:
            reader.close()


def main(args: list[str] | None = None) -> int:
    """Run the player until the bag ends (or forever with ``loop``)."""
    rclpy.init(args=args)
    executor = SingleThreadedExecutor()
    node = None
    status = 0
    try:
        node = BagPlayer()
        executor.add_node(node)
        while rclpy.ok() and not node.finished.is_set():
            executor.spin_once(timeout_sec=0.1)
        if node.error:
            print(f"error: {node.error}", file=sys.stderr)
            status = 1
    except BagError as exc:
        print(f"error: {exc}", file=sys.stderr)
        status = 1
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.stop()
            node.destroy_node()
        executor.shutdown()
        if rclpy.ok():
            rclpy.shutdown()
    return status


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
