"""Calling sysid_node's ~/identify from your own rclpy node, and reading the model.

Run sysid_node and a bag replay first, then:  python examples/identify_from_node.py
(with ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST and the same ROS_DOMAIN_ID).
"""

import json

import rclpy
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String
from std_srvs.srv import Trigger


class ModelUser(Node):
    """Asks for an identification and prints the model when it arrives."""

    def __init__(self) -> None:
        super().__init__("model_user")
        self.client = self.create_client(Trigger, "/spm_sysid/identify")
        # ~/model is latched: subscribe reliable + transient-local to get the last one
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.create_subscription(String, "/spm_sysid/model", self.on_model, latched)
        self.model = None

    def identify(self) -> None:
        self.client.wait_for_service()
        future = self.client.call_async(Trigger.Request())
        rclpy.spin_until_future_complete(self, future)
        answer = future.result()
        self.get_logger().info(("identified: " if answer.success else "refused: ")
                               + answer.message)

    def on_model(self, msg: String) -> None:
        self.model = json.loads(msg.data)
        terms = " + ".join(f"{c:.3f}*{t}" for c, t in zip(self.model["coefficients"],
                                                          self.model["terms"]))
        self.get_logger().info(f"model: y(t) = {terms}")


def main() -> None:
    rclpy.init()
    node = ModelUser()
    try:
        node.identify()
        while node.model is None:
            rclpy.spin_once(node, timeout_sec=0.5)
    finally:
        node.destroy_node()
        rclpy.shutdown()


if __name__ == "__main__":
    main()
