"""``sysid_node``: record input/output topics, identify on a service call, publish.

The node only wires its parts (:mod:`spm_sysid.ros.node`): parameters from the
settings schema, a recorder that turns messages into samples in a
:class:`~spm_sysid.core.stream.buffer.SampleBuffer`, identifications that run
:func:`spm_sysid.core.jobs.run_job` in a worker process (so the search never
blocks recording, and uses the other core), a publisher of the model on its
latched topics, the online prediction and validity, and the automatic
re-identification. Its own code is the services, the action and the
diagnostics. Interface: see docs/ros_interface.md.
"""

from __future__ import annotations

import sys
import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.node import Node
from spm_sysid_interfaces.action import Identify
from spm_sysid_interfaces.srv import GetModel
from std_srvs.srv import Trigger

from ..core.progress import Progress
from ..core.stream.diagnostics import dashboard_status, diagnostic_statuses, online_status
from .common import LATCHED, REQUESTS, CallbackErrors, run_node
from .node.identification import Code, Identification
from .node.online import OnlinePart
from .node.parameters import NodeParameters, parameter_descriptor
from .node.publishing import ModelPublisher, model_size
from .node.recording import Recorder, describe
from .node.reidentify import Reidentification
from .typed import feedback_message

__all__ = ["LATCHED", "SysidNode", "main", "parameter_descriptor"]


class SysidNode(Node):
    """Records signals, identifies on request, publishes the validated model."""

    def __init__(self) -> None:
        super().__init__("spm_sysid")
        self.callback_errors = CallbackErrors(self.get_logger())  # run_node counts into it
        self.params = NodeParameters(self)
        p = self.params.values
        self.recorder = Recorder(self, p, self.params.channels, self.params.out_channels)
        self.diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.online = OnlinePart(self, lambda: self.params.values, self.recorder,
                                 on_invalid=lambda: self.reidentify.maybe_start())
        self.publisher = ModelPublisher(self, on_model=self.online.start)
        self.identification = Identification(self, self.params, self.recorder,
                                              publish=self._publish_result)
        self.reidentify = Reidentification(self, lambda: self.params.values, self.recorder,
                                           self.identification, self.online,
                                           publish=self._publish_result,
                                           on_done=self._publish_diagnostics)
        # One executor thread does everything quickly (rclpy's multi-threaded executor
        # takes too long per message for 2 kHz). ~/identify is a coroutine that awaits
        # the worker process, so recording goes on while it runs; its group is
        # reentrant so a second request is answered (refused) meanwhile.
        services = ReentrantCallbackGroup()
        self.create_service(Trigger, "~/identify", self._on_identify, callback_group=services,
                            qos_profile=REQUESTS)
        self.create_service(GetModel, "~/get_model", self._on_get_model,
                            callback_group=services, qos_profile=REQUESTS)
        # the action shares the Trigger's name (actions live in their own namespace)
        self.action = ActionServer(self, Identify, "~/identify", self._execute_goal,
                                   goal_callback=self._on_goal,
                                   cancel_callback=self._on_cancel, callback_group=services,
                                   goal_service_qos_profile=REQUESTS,
                                   result_service_qos_profile=REQUESTS,
                                   cancel_service_qos_profile=REQUESTS)
        self.create_service(Trigger, "~/clear", self._on_clear, callback_group=services,
                            qos_profile=REQUESTS)
        self.dashboard = self.dashboard_server = None
        if p["dashboard_port"]:
            self._start_dashboard(p)
        self.create_timer(p["diagnostics_period"], self._publish_diagnostics)
        self.create_timer(1.0, self._online_tick)
        self.get_logger().info(
            f"recording inputs {describe(self.params.channels)} and outputs "
            f"{describe(self.params.out_channels)}; buffer of {p['buffer_capacity']} samples")
        if p["model_path"]:
            self.publisher.republish_saved(p["model_path"])

    def _start_dashboard(self, p: dict) -> None:
        """Serve the live page (``dashboard_port``); a failure is one error line, no crash."""
        from .node.dashboard import STATUS_PERIOD, Dashboard
        from .node.dashboard_server import DashboardError, DashboardServer

        board = Dashboard(p["dashboard_seconds"])
        try:
            self.dashboard_server = DashboardServer(board, p["dashboard_port"],
                                                    p["dashboard_host"], p["dashboard_token"])
        except DashboardError as exc:
            self.get_logger().error(str(exc))
            return
        self.dashboard = self.online.dashboard = board
        self._update_dashboard()
        self.create_timer(STATUS_PERIOD, self._update_dashboard)
        self.get_logger().info(self.dashboard_server.describe())

    def _update_dashboard(self) -> None:
        """The dashboard's snapshot of the node (read-only to its server's threads)."""
        from .node.dashboard import node_status

        ident, pub = self.identification, self.publisher
        self.dashboard.update(node_status(
            self.get_fully_qualified_name(), self.online.session,
            None if ident.started is None else (ident.progress, ident.started),
            pub.model, pub.doc, pub.restored_from))

    # -- services and the action ---------------------------------------------------------
    def _on_clear(self, request, response):
        response.success = True
        response.message = f"cleared {self.recorder.buffer.clear()} samples"
        self.get_logger().info(response.message)
        return response

    async def _on_identify(self, request, response):
        """``~/identify`` (Trigger): the action's job, answered as a paragraph."""
        out = await self.identification.run()
        response.success = out.code in (Code.NONE, Code.DIVERGED)
        response.message = out.message
        return response

    def _on_goal(self, goal) -> GoalResponse:
        # Every goal is accepted: a second one while one runs ends at once with BUSY and
        # the reason, which a rejection could not carry.
        return GoalResponse.ACCEPT

    def _on_cancel(self, goal_handle) -> CancelResponse:
        self.identification.cancel(goal_handle)
        return CancelResponse.ACCEPT

    async def _execute_goal(self, goal_handle) -> Identify.Result:
        """``~/identify`` (action): feedback while it runs; a typed result with a code."""
        goal = goal_handle.request
        t0 = time.monotonic()

        def feedback(progress: Progress) -> None:  # the worker's reader thread
            try:
                goal_handle.publish_feedback(feedback_message(progress, time.monotonic() - t0))
            except Exception:  # noqa: BLE001 - the goal ended meanwhile: nothing to tell
                pass

        out = await self.identification.run(list(goal.setting_names),
                                            list(goal.setting_values), goal.bag_path,
                                            feedback=feedback, goal=goal_handle)
        result = Identify.Result(error_code=out.code, message=out.message)
        if out.result is not None:
            self.publisher.fill(result)
        if out.code == Code.CANCELED and goal_handle.is_cancel_requested:
            goal_handle.canceled()
        elif out.code in (Code.NONE, Code.DIVERGED):
            goal_handle.succeed()
        else:
            goal_handle.abort()
        return result

    def _on_get_model(self, request, response):
        """``~/get_model``: the current model, for nodes that cannot use latched topics."""
        publisher = self.publisher
        if publisher.doc is None:
            response.available = False
            response.message = "no model yet: call ~/identify (or set model_path)"
            return response
        response.available = True
        publisher.fill(response)
        response.message = (model_size(publisher.model)
                            + (f", restored from {publisher.restored_from}"
                               if publisher.restored_from else ""))
        return response

    # -- results, online, diagnostics ----------------------------------------------------
    def _publish_result(self, result, model_path: str) -> None:
        """Save (when asked) and publish a result; then the diagnostics say so."""
        self.publisher.publish_result(result, model_path)
        if self.dashboard is not None:
            self.dashboard.new_result(result)
        self.identification.last_error = None
        self._publish_diagnostics()

    def _online_tick(self) -> None:
        """Every second: validity statistics, and the re-identification policy."""
        self.online.publish_validity()
        self.reidentify.maybe_start()

    def _publish_diagnostics(self) -> None:
        rec, ident, worker = self.recorder, self.identification, self.identification.worker
        statuses = diagnostic_statuses(
            self.get_fully_qualified_name(), rec.buffer.stats_dict(),
            field_errors=rec.field_errors, unset_stamps=rec.unset.count,
            worker_ready=worker.ready, worker_restarts=worker.restarts,
            type_mismatches=list(rec.type_mismatch.values()), namesakes=rec.namesakes,
            running=None if ident.started is None else (
                ident.progress or Progress("checking data"), time.monotonic() - ident.started),
            last_error=ident.last_error, model=self.publisher.doc,
            restored_from=self.publisher.restored_from,
            callback_errors=self.callback_errors.count,
            worker_failure=worker.start_failure, unnamed=rec.unnamed,
            ignored_parameters=self.params.unknown)
        statuses.append(online_status(self.get_fully_qualified_name(), self.online.session,
                                      {**self.reidentify.counts,
                                       "online_errors": self.online.errors},
                                      self.online.ranges.values()))
        server = self.dashboard_server
        if server is not None:
            statuses.append(dashboard_status(self.get_fully_qualified_name(), server.url,
                                             server.requests, dict(server.counts)))
        msg = DiagnosticArray(status=[DiagnosticStatus(
            level=bytes([s.level]), name=s.name, message=s.message, hardware_id="spm_sysid",
            values=[KeyValue(key=k, value=v) for k, v in s.values.items()])
            for s in statuses])
        msg.header.stamp = self.get_clock().now().to_msg()
        self.diag_pub.publish(msg)

    def close(self) -> None:
        """Stop the worker process (a running search is killed) and the dashboard."""
        self.identification.close()
        if self.dashboard_server is not None:
            self.dashboard_server.close()


def main(args: list[str] | None = None) -> int:
    """Run the node until interrupted (SIGINT or SIGTERM end it within a second or two)."""
    from rclpy.exceptions import ParameterException

    # a start-up parameter of the wrong type (-p criterion:=1) is one error line too
    return run_node(SysidNode, errors=(ValueError, TypeError, ParameterException), args=args,
                    finish=lambda node, interrupted: 0)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
