"""Your own rclpy node asking sysid_node for a model through its Identify action.

It sends a goal (optionally with setting overrides and a bag to identify on),
prints the feedback as it comes, and reads the typed result: an error code and
each output's model as ``spm_sysid_interfaces/msg/NarxModel`` (terms with their
factors, coefficients with standard errors) with its validation report (one
output, or several joints of one coupled model). Ctrl-C cancels
the goal; the node then keeps its previous model.

Run sysid_node first (and replay a bag into it, or pass a bag), then:

    python examples/identify_action_client.py                    # on the node's buffer
    python examples/identify_action_client.py bags/robot_arm criterion=bic

with ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST and the node's ROS_DOMAIN_ID.
"""

import sys

import rclpy
from rclpy.action import ActionClient
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from spm_sysid_interfaces.action import Identify


class ModelClient(Node):
    """Sends one Identify goal and keeps the typed result."""

    def __init__(self) -> None:
        super().__init__("model_client")
        self.client = ActionClient(self, Identify, "/spm_sysid/identify")

    def identify(self, bag_path: str = "", **overrides: str) -> Identify.Result:
        if not self.client.wait_for_server(timeout_sec=30.0):
            raise RuntimeError("no /spm_sysid/identify action: is sysid_node running?")
        goal = Identify.Goal(bag_path=bag_path, setting_names=list(overrides),
                             setting_values=list(overrides.values()))
        sent = self.client.send_goal_async(goal, feedback_callback=self.on_feedback)
        rclpy.spin_until_future_complete(self, sent)
        handle = sent.result()
        result = handle.get_result_async()
        try:
            rclpy.spin_until_future_complete(self, result)
        except KeyboardInterrupt:  # cancel the search; the node keeps its old model
            rclpy.spin_until_future_complete(self, handle.cancel_goal_async())
            rclpy.spin_until_future_complete(self, result, timeout_sec=10.0)
        return result.result().result

    def on_feedback(self, message) -> None:
        fb = message.feedback
        self.get_logger().info(f"{fb.phase}: step {fb.step}, best {fb.best_value:.2f}, "
                               f"{fb.structures_evaluated} structures, {fb.elapsed:.1f} s")


def main() -> int:
    bag = sys.argv[1] if len(sys.argv) > 1 else ""
    overrides = dict(arg.split("=", 1) for arg in sys.argv[2:])
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = ModelClient()
    try:
        result = node.identify(bag, **overrides)
        if result.error_code not in (Identify.Result.NONE, Identify.Result.DIVERGED):
            print(f"no model (error code {result.error_code}): {result.message}")
            return 1
        # result.models: every output's model and report (one output: the same as
        # result.model and result.report; several joints: one coupled model)
        models = result.models
        several = len(models.models) > 1
        for name, model, report in zip(models.output_names, models.models, models.reports):
            print(("output " + name + ": " if several else "")
                  + f"{model.criterion.upper()} {model.criterion_value:.2f}, "
                  f"{len(model.terms)} terms, free-run fit {model.free_run_fit_percent:.1f} %"
                  + (" (coupled)" if several else ""))
            for term, coef, se in zip(model.terms, model.coefficients, model.standard_errors):
                factors = " * ".join(f"{f.signal}[t-{f.lag}]^{f.power}" for f in term.factors)
                print(f"  {coef:+.6f} (+- {se:.1e})  {term.name:<16} = {factors or '1'}")
            failed = [t.name for t in report.correlation_tests if not t.passed]
            print("correlation tests outside the band: " + (", ".join(failed) or "none"))
        if several:
            failed = [t.name for t in models.cross_correlation_tests if not t.passed]
            print(f"joint {models.criterion.upper()} {models.joint_criterion_value:.2f}; residual "
                  "cross-correlation outside the band: " + (", ".join(failed) or "none"))
        return 0
    finally:
        node.destroy_node()
        rclpy.shutdown()


if __name__ == "__main__":
    sys.exit(main())
