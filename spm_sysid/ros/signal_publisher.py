"""Publish input/output samples on the robot-arm topics at a fixed rate.

A stand-in for a robot driver, used by the node benchmark and the tests::

    python -m spm_sysid.ros.signal_publisher RATE COUNT [--data robot_arm|PATH|ramp]
        [--stamps index|wall|zero] [--start-ns S] [--output-offset-ns D] [--nan-every K]
        [--backpressure-timeout SECONDS]

It waits until both topics have a subscriber (plus a settle second, so the
subscriber's side of discovery is complete), publishes COUNT messages per topic
(the data repeat if shorter) with the same stamp on both topics -- ``start + k /
rate`` (``index``) or the wall clock (``wall``) -- shifts output stamps by D ns,
replaces every K-th output with NaN, then prints one JSON line: what it did.
Publishers are reliable and keep-all, so nothing is dropped on this side: when
the subscriber falls behind and the middleware's send queue is full, a publish
waits (up to :data:`BACKPRESSURE_TIMEOUT` seconds for the subscriber to catch up)
and is tried again; the waits are counted (``"blocked"``), and a subscriber that
does not catch up ends the run with an error line and exit status 1, never a
traceback.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time

__all__ = ["BACKPRESSURE_TIMEOUT", "main"]

#: Seconds a publish may wait for a full send queue to drain before giving up.
BACKPRESSURE_TIMEOUT = 10.0
#: Seconds to wait at the end for every subscriber to acknowledge every message.
ACK_TIMEOUT = 30.0


def rclpy_duration(seconds: float):
    from rclpy.duration import Duration

    return Duration(nanoseconds=int(seconds * 1e9))


def _publish(pub, msg, stats: dict, timeout: float = BACKPRESSURE_TIMEOUT) -> None:
    """Publish, waiting out back-pressure (a full reliable queue) and counting the waits."""
    import rclpy
    from rclpy._rclpy_pybind11 import RCLError

    deadline = time.monotonic() + timeout
    while True:
        if not rclpy.ok():  # SIGINT/SIGTERM shut the context down
            raise KeyboardInterrupt
        try:
            pub.publish(msg)
            return
        except RCLError as exc:
            if not rclpy.ok():
                raise KeyboardInterrupt from None
            if time.monotonic() > deadline:
                raise RuntimeError(f"the subscriber did not take messages for "
                                   f"{timeout:g} s ({exc})") from None
            stats["blocked"] += 1
            pub.wait_for_all_acked(rclpy_duration(0.05))


def main(argv: list[str] | None = None) -> int:
    """Command-line entry; returns the exit status."""
    a = _parser().parse_args(argv)

    import rclpy
    from geometry_msgs.msg import AccelStamped, WrenchStamped
    from rclpy.node import Node
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

    u, y = _signals(a.data, a.count)
    rclpy.init()
    node = Node("signal_publisher")
    qos = QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE)
    pub_u = node.create_publisher(WrenchStamped, a.input_topic, qos)
    pub_y = node.create_publisher(AccelStamped, a.output_topic, qos)
    try:
        while pub_u.get_subscription_count() < 1 or pub_y.get_subscription_count() < 1:
            time.sleep(0.05)
        time.sleep(1.0)
        print(json.dumps({"started": True}), flush=True)
        return _publish_all(a, u, y, pub_u, pub_y)
    except KeyboardInterrupt:
        return 130
    finally:
        node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()


def _parser() -> argparse.ArgumentParser:
    """The command line: rate, count, the data and what to do to stamps and values."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("rate", type=float, help="messages per second per topic")
    p.add_argument("count", type=int, help="messages per topic")
    p.add_argument("--data", default="robot_arm",
                   help="robot_arm (default), ramp, or a data file path")
    p.add_argument("--stamps", choices=("index", "wall", "zero"), default="index",
                   help="header stamps: start + k / rate, the wall clock, or left at 0 "
                        "(a driver that never fills them in)")
    p.add_argument("--start-ns", type=int, default=0)
    p.add_argument("--output-offset-ns", type=int, default=0)
    p.add_argument("--nan-every", type=int, default=0)
    p.add_argument("--backpressure-timeout", type=float, default=BACKPRESSURE_TIMEOUT,
                   help="seconds a publish may wait for a full send queue to drain")
    p.add_argument("--input-topic", default="/robot_arm/torque")
    p.add_argument("--output-topic", default="/robot_arm/acceleration")
    return p


def _signals(data: str, count: int):
    """The input and output to publish: a ramp, the robot-arm data, or a data file."""
    from ..core.record import DataSpec, load_record

    if data == "ramp":
        return [float(k) for k in range(count)], [-float(k) for k in range(count)]
    record = load_record(DataSpec.from_values({}, data=None if data == "robot_arm" else data))
    return record.u, record.y


def _publish_all(a, u, y, pub_u, pub_y) -> int:
    """``a.count`` samples at ``a.rate``, then wait for every subscriber's acknowledgement.

    Prints one JSON line of counts at the end (or when interrupted or refused).
    """
    from geometry_msgs.msg import AccelStamped, WrenchStamped

    w, acc = WrenchStamped(), AccelStamped()
    nans = late = 0
    stats = {"blocked": 0}
    t0 = time.monotonic()
    for k in range(a.count):
        delay = t0 + k / a.rate - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        elif delay < -0.01:
            late += 1
        ns = (time.time_ns() if a.stamps == "wall" else 0 if a.stamps == "zero"
              else a.start_ns + round(k * 1e9 / a.rate))
        w.header.stamp.sec, w.header.stamp.nanosec = divmod(ns, 10**9)
        acc.header.stamp.sec, acc.header.stamp.nanosec = divmod(
            ns + a.output_offset_ns if ns else 0, 10**9)
        w.wrench.torque.z = float(u[k % len(u)])
        acc.accel.linear.x = float(y[k % len(y)])
        if a.nan_every and k % a.nan_every == 0:
            acc.accel.linear.x = math.nan
            nans += 1
        try:
            _publish(pub_u, w, stats, a.backpressure_timeout)
            _publish(pub_y, acc, stats, a.backpressure_timeout)
        except KeyboardInterrupt:
            print(json.dumps({"published": k, "nans": nans, "late": late, **stats,
                              "interrupted": True}), flush=True)
            return 130
        except RuntimeError as exc:
            print(json.dumps({"published": k, "nans": nans, "late": late, **stats,
                              "error": str(exc)}), flush=True)
            print(f"error: {exc}; {k} of {a.count} samples published", file=sys.stderr)
            return 1
    elapsed = time.monotonic() - t0
    # every subscriber acknowledged every message before the publishers go away (a
    # fixed sleep lost the tail on a loaded machine: 56 266 of 60 000 arrived)
    confirmed = all(pub.wait_for_all_acked(rclpy_duration(ACK_TIMEOUT))
                    for pub in (pub_u, pub_y))
    print(json.dumps({"published": a.count, "nans": nans, "seconds": elapsed,
                      "late": late, "delivery_confirmed": confirmed, **stats}), flush=True)
    if not confirmed:
        print(f"warning: not every message was acknowledged within {ACK_TIMEOUT:g} s",
              file=sys.stderr)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
