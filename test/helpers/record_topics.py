"""Test helper process: subscribe to the robot-arm topics with a default QoS and
print what arrived as JSON (values and header stamps, in arrival order)."""

import json
import sys
import time

import rclpy
from geometry_msgs.msg import AccelStamped, WrenchStamped
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

# reliable and keep-all: a burst waits instead of being dropped on a loaded machine
QOS = QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE,
                 durability=DurabilityPolicy.VOLATILE)


def main() -> None:
    # expected count on both topics ("N"), or per topic ("NU,NY"); stops when reached
    counts = [int(x) for x in sys.argv[1].split(",")]
    expected_u, expected_y = counts if len(counts) == 2 else counts * 2
    timeout = float(sys.argv[2])
    in_topic = sys.argv[3] if len(sys.argv) > 3 else "/robot_arm/torque"
    out_topic = sys.argv[4] if len(sys.argv) > 4 else "/robot_arm/acceleration"
    rclpy.init()
    node = Node("test_recorder")
    got = {"u": [], "y": [], "tu": [], "ty": []}

    def on_u(m):
        got["u"].append(m.wrench.torque.z)
        got["tu"].append(m.header.stamp.sec * 10**9 + m.header.stamp.nanosec)

    def on_y(m):
        got["y"].append(m.accel.linear.x)
        got["ty"].append(m.header.stamp.sec * 10**9 + m.header.stamp.nanosec)

    node.create_subscription(WrenchStamped, in_topic, on_u, QOS)
    node.create_subscription(AccelStamped, out_topic, on_y, QOS)
    print("ready", flush=True)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.05)
        if len(got["u"]) >= expected_u and len(got["y"]) >= expected_y:
            break
    # a grace period catches anything beyond the expected count
    end = time.monotonic() + 1.0
    while time.monotonic() < end:
        rclpy.spin_once(node, timeout_sec=0.05)
    print(json.dumps(got), flush=True)
    node.destroy_node()
    rclpy.shutdown()


if __name__ == "__main__":
    main()
