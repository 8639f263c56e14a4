"""Test helper process: publish input/output messages at a fixed rate.

usage: publish_signals.py RATE COUNT [--data robot_arm|ramp] [--nan-every K]
       [--output-offset-ns D] [--start-ns S]
Waits for one subscriber per topic (plus a settle second), publishes COUNT
messages per topic with matching stamps (the output stamp shifted by D), and
prints one JSON line: what it published.
"""

import argparse
import json
import math
import time

import rclpy
from geometry_msgs.msg import AccelStamped, WrenchStamped
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

from spm_sysid.core.data import load_robot_arm


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("rate", type=float)
    p.add_argument("count", type=int)
    p.add_argument("--data", default="robot_arm")
    p.add_argument("--nan-every", type=int, default=0)
    p.add_argument("--output-offset-ns", type=int, default=0)
    p.add_argument("--start-ns", type=int, default=0)
    a = p.parse_args()
    if a.data == "robot_arm":
        u, y = load_robot_arm()
    else:
        u = [float(k) for k in range(a.count)]
        y = [-float(k) for k in range(a.count)]
    rclpy.init()
    node = Node("test_signal_publisher")
    qos = QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE)
    pw = node.create_publisher(WrenchStamped, "/robot_arm/torque", qos)
    pa = node.create_publisher(AccelStamped, "/robot_arm/acceleration", qos)
    while pw.get_subscription_count() < 1 or pa.get_subscription_count() < 1:
        time.sleep(0.05)
    time.sleep(1.0)
    print(json.dumps({"started": True}), flush=True)
    w, acc = WrenchStamped(), AccelStamped()
    period = 1e9 / a.rate
    nans = 0
    t0 = time.monotonic()
    for k in range(a.count):
        delay = t0 + k / a.rate - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        ns = a.start_ns + int(round(k * period))
        w.header.stamp.sec, w.header.stamp.nanosec = divmod(ns, 10**9)
        acc.header.stamp.sec, acc.header.stamp.nanosec = divmod(ns + a.output_offset_ns, 10**9)
        i = k % len(u)
        w.wrench.torque.z = float(u[i])
        acc.accel.linear.x = float(y[i])
        if a.nan_every and k % a.nan_every == 0:
            acc.accel.linear.x = math.nan
            nans += 1
        pw.publish(w)
        pa.publish(acc)
    elapsed = time.monotonic() - t0
    time.sleep(1.0)  # let reliable delivery finish before the publisher goes away
    print(json.dumps({"published": a.count, "nans": nans, "seconds": elapsed}), flush=True)
    node.destroy_node()
    rclpy.shutdown()


if __name__ == "__main__":
    main()
