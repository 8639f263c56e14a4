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
``qos_depth`` (int, 10000)  keep-last depth of the reliable, volatile publishers;
    a default subscriber (reliable, volatile) matches them
``wait_for_subscribers`` (int, 1)  wait until each topic has this many matched
    subscribers before playing; 0 plays at once (messages sent before a
    subscriber matched are lost to it)
``wait_timeout`` (double, 30.0)  longest wait for subscribers; when it runs out
    the player publishes nothing and exits with status 1
``settle_time`` (double, 1.0)  seconds to wait after the subscribers matched:
    discovery completes on the subscriber's side a little after the publisher
    sees it, and a reliable, volatile subscriber misses what was sent before
``ack_timeout`` (double, 10.0)  at the end, longest wait for every reliable
    subscriber to acknowledge every message

Delivery: before exiting, the player waits until every reliable subscriber
has acknowledged everything (``Publisher.wait_for_all_acked``) and reports per
topic how many messages it published and whether delivery was confirmed.

Exit status: 0 when every message was published and (for reliable
subscribers) acknowledged; 1 for an error (unreadable bag, bad parameters, no
subscriber within ``wait_timeout``); 3 when delivery could not be confirmed
within ``ack_timeout``; 130 when interrupted (the counts so far are printed).

Replaying a bag again, or ``loop:=true``, publishes the same stamps again:
``sysid_node`` treats stamps that go back as the start of a new segment (a new
timeline, never fitted across) after ``resync_samples`` samples, and logs it.
"""

from __future__ import annotations

import math
import sys
import threading
import time
from collections import Counter
from pathlib import Path

from rcl_interfaces.msg import ParameterDescriptor
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from ..core.errors import BagError
from ..core.io.bagio import open_bag
from .common import asks_for_help, message_class, run_node

__all__ = ["BagPlayer", "main"]


#: The player's parameters: name, default, description (all read-only).
_PARAMETERS = (
    ("bag", "", "bag directory or .mcap file"),
    ("rate", 1.0, "playback speed factor (> 0)"),
    ("start_delay", 0.0, "seconds before the first message"),
    ("loop", False, "replay from the start at the end"),
    ("topics", [""], "topics to play (empty: all)"),
    ("remap", [""], "from:=to topic renames"),
    ("qos_depth", 10000, "keep-last depth of the publishers"),
    ("wait_for_subscribers", 1,
     "matched subscribers per topic before playing (0: play at once)"),
    ("wait_timeout", 30.0, "longest wait for subscribers, seconds"),
    ("settle_time", 1.0, "seconds to wait after subscribers matched"),
    ("ack_timeout", 10.0, "longest wait at the end for subscribers to acknowledge, seconds"),
)


def _remaps(entries: list[str]) -> dict[str, str]:
    """``from:=to`` entries as a dict, or a BagError naming the bad entry."""
    remap = {}
    for item in (r for r in entries if r):
        src, sep, dst = item.partition(":=")
        if not sep or not src or not dst:
            raise BagError(f"remap entry {item!r} must look like from:=to")
        remap[src] = dst
    return remap


class BagPlayer(Node):
    """Publishes a bag's messages on their topics with the recorded timing."""

    def __init__(self) -> None:
        super().__init__("bag_player")
        p = self._read_parameters()
        self.bag = Path(p["bag"])
        self.rate = float(p["rate"])
        self.start_delay = max(0.0, float(p["start_delay"]))
        self.loop = bool(p["loop"])
        self.wait_for = int(p["wait_for_subscribers"])
        self.wait_timeout = float(p["wait_timeout"])
        self.settle_time = max(0.0, float(p["settle_time"]))
        self.ack_timeout = float(p["ack_timeout"])
        selected = [t for t in p["topics"] if t]
        remap = _remaps(p["remap"])
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
        self.published: Counter[str] = Counter({t: 0 for t in self.topics})
        self.confirmed: dict[str, bool | None] = {}
        self.subscribers: dict[str, int] = {}
        self.finished = threading.Event()
        self.error: str | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._play, name="bag-playback", daemon=True)
        self._thread.start()

    def _read_parameters(self) -> dict:
        """The node's parameters (read-only), declared, read and checked."""
        for name, default, description in _PARAMETERS:
            self.declare_parameter(name, default, ParameterDescriptor(
                description=description, read_only=True))
        p = {name: self.get_parameter(name).value for name, _, _ in _PARAMETERS}
        from .node.parameters import unknown_overrides, unknown_text

        for name in unknown_overrides(self):  # ROS would keep them unused, unsaid
            self.get_logger().warning(unknown_text(
                name, [n for n, _, _ in _PARAMETERS], ", ".join(n for n, _, _ in _PARAMETERS)))
        if not p["bag"]:
            raise BagError("parameter 'bag' is required (--ros-args -p bag:=PATH)")
        if not (p["rate"] > 0 and math.isfinite(p["rate"])):
            raise BagError(f"parameter 'rate' must be > 0, got {p['rate']}")
        for name in ("start_delay", "wait_timeout", "settle_time", "ack_timeout"):
            if not (p[name] >= 0 and math.isfinite(p[name])):
                raise BagError(f"parameter '{name}' must be >= 0 seconds, got {p[name]}")
        if p["wait_for_subscribers"] < 0 or p["qos_depth"] < 1:
            raise BagError("parameters 'wait_for_subscribers' must be >= 0 and 'qos_depth' "
                           ">= 1")
        return p

    def stop(self) -> None:
        """Ask the playback thread to end."""
        self._stop.set()

    def _wait_for_subscribers(self) -> bool:
        """Wait until every topic has its subscribers, then let discovery settle."""
        deadline = time.monotonic() + self.wait_timeout
        while not self._stop.is_set():
            missing = sorted(self._out_name(t) for t, pub in self.publishers_by_topic.items()
                             if pub.get_subscription_count() < self.wait_for)
            if not missing:
                self._stop.wait(self.settle_time)
                return True
            if time.monotonic() >= deadline:
                self.error = (
                    f"no subscriber on {', '.join(missing)} after {self.wait_timeout:g} s; "
                    "nothing was published (start the subscribers first, raise "
                    "wait_timeout, or set wait_for_subscribers:=0 to play anyway)")
                return False
            time.sleep(0.02)
        return False

    def _out_name(self, topic: str) -> str:
        return self.publishers_by_topic[topic].topic_name

    def _confirm_delivery(self) -> None:
        """Wait until every reliable subscriber acknowledged everything (per topic)."""
        deadline = time.monotonic() + self.ack_timeout
        for topic, pub in self.publishers_by_topic.items():
            left = max(0.0, deadline - time.monotonic())
            self.confirmed[topic] = bool(pub.wait_for_all_acked(
                Duration(nanoseconds=int(left * 1e9))))

    def report(self) -> str:
        """Per topic: published, subscribers when playback began, delivery confirmed."""
        parts = []
        for topic in sorted(self.topics):
            state = {True: "delivery confirmed", False: "delivery NOT confirmed",
                     None: "delivery not checked"}[self.confirmed.get(topic)]
            subs = self.subscribers.get(topic, "?")
            parts.append(f"{self._out_name(topic)}: {self.published[topic]} published, "
                         f"{subs} subscriber(s), {state}")
        return "; ".join(parts)

    @property
    def delivery_confirmed(self) -> bool:
        return bool(self.confirmed) and all(self.confirmed.values())

    def _play(self) -> None:
        try:
            if self.wait_for > 0 and not self._wait_for_subscribers():
                return
            if self.start_delay:
                self._stop.wait(self.start_delay)
            self.subscribers = {t: pub.get_subscription_count()
                                for t, pub in self.publishers_by_topic.items()}
            self.get_logger().info(
                f"playing {self.bag} at {self.rate:g}x: {', '.join(sorted(self.topics))}")
            while not self._stop.is_set():
                self._play_once()
                if not self.loop:
                    break
            if not self._stop.is_set():
                self._confirm_delivery()
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


def _finish(node: BagPlayer, interrupted: bool) -> int:
    """Print the per-topic report; the exit status (see the module docstring)."""
    node.stop()
    if interrupted:
        print(f"interrupted: {node.report()}", file=sys.stderr)
        return 130
    if node.error:
        print(f"error: {node.error}", file=sys.stderr)
        return 1
    line = f"published {sum(node.published.values())} messages ({node.report()})"
    if node.delivery_confirmed:
        print(line, file=sys.stderr)
        return 0
    print(f"error: {line}: not every subscriber acknowledged every message within "
          f"ack_timeout ({node.ack_timeout:g} s)", file=sys.stderr)
    return 3


BAG_PLAYER_USAGE = """usage: bag_player --ros-args -p bag:=PATH [-p rate:=1.0] [-p loop:=true] ...

Replays a rosbag2 bag (MCAP) onto its topics with the recorded timing, at
rate times real time, and says how many messages it published per topic.
Parameters: bag, rate, start_delay, loop, topics, remap, qos_depth,
wait_for_subscribers, wait_timeout, settle_time (docs/ros.md, "bag_player").

  bag_player --ros-args -p bag:=bags/robot_arm -p rate:=10.0
"""


def main(args: list[str] | None = None) -> int:
    """Run the player until the bag ends (or forever with ``loop``); see the exit statuses."""
    if asks_for_help(args):
        print(BAG_PLAYER_USAGE, end="")
        return 0
    return run_node(BagPlayer, until=lambda node: node.finished.is_set(), errors=(BagError,),
                    finish=_finish, args=args)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
