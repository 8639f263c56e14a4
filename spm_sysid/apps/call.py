"""Calling the node without the ``ros2`` command line.

``spm-sysid call identify`` sends a goal to the node's ``~/identify`` action
(:func:`identify_goal`): a progress line from its feedback, Ctrl-C cancels the
goal, the typed result's code decides the exit status. ``spm-sysid call clear``
and ``call identify --trigger`` use the ``std_srvs/Trigger`` services
(:func:`call_trigger`). ``spm-sysid call watch`` prints the model's validity as
it changes (:func:`watch_validity`). Another rclpy node can do the same with
its own client (``examples/identify_action_client.py``,
``examples/identify_from_node.py``).
"""

from __future__ import annotations

import json
import math
import sys
import time

import rclpy
from rclpy.node import Node

from ..ros.client import call_trigger, identify_goal, wait_for_model
from ..ros.common import LATCHED

__all__ = ["FeedbackLine", "feedback_text", "main", "model_summary", "validity_line",
           "watch_validity"]

def feedback_text(fb) -> str:
    """One ``Identify`` feedback message as the node logs its progress (one formatter)."""
    from ..core.progress import Progress

    bound = fb.best_value - fb.gap if fb.gap == fb.gap else math.nan
    return Progress(fb.phase, fb.step, fb.total, fb.best_value, fb.structures_evaluated, bound,
                    fb.elapsed).line()


def model_summary(doc: dict) -> str:
    """A model document for reading: equation, coefficient table, fits, certification."""
    from ..core.model.mimo import MIMO_SCHEMA
    from ..core.model.narx import NarxModel
    from ..core.search.certify import describe_certificate

    if doc.get("schema") == MIMO_SCHEMA:
        parts = [f"coupled model of {len(doc['outputs'])} outputs "
                 f"({', '.join(doc['outputs'])})"]
        parts += [model_summary(m) for m in doc["models"]]
        return "\n\n".join(parts)
    model = NarxModel.from_dict(doc)
    lines = [model.equation(), model.coefficient_table()]
    meta = doc.get("metadata") or {}
    val = meta.get("validation") or {}
    fits = []
    for key, label in (("one_step", "one-step"), ("free_run", "free-run")):
        fit = (val.get(key) or {}).get("fit_percent")
        if fit is not None:
            fits.append(f"{label} fit {fit:.1f} %")
    if val.get("diverged_at") is not None:
        fits.append(f"the free run diverged at sample {val['diverged_at']}")
    if fits:
        lines.append("fits: " + ", ".join(fits))
    crit = doc.get("criterion") or {}
    text = f"criterion: {str(crit.get('name', '?')).upper()}"
    if crit.get("value") is not None:
        text += f" {crit['value']:.2f}"
    cert = describe_certificate(meta.get("certificate"))
    lines.append(text + (f", {cert}" if cert else ""))
    for w in meta.get("warnings") or []:
        lines.append(f"warning: {w}")
    return "\n".join(lines)


class FeedbackLine:
    """The feedback as one progress line (redrawn on a terminal, a line per phase else)."""

    def __init__(self, stream=sys.stderr) -> None:
        self.stream, self.tty = stream, stream.isatty()
        self.phase, self.last = None, 0.0

    def __call__(self, fb) -> None:
        now = time.monotonic()
        if not self.tty and fb.phase == self.phase and now - self.last < 5.0:
            return
        text = feedback_text(fb)
        if self.tty:
            self.stream.write("\r\x1b[K" + text)
        else:
            self.stream.write(text + "\n")
        self.stream.flush()
        self.phase, self.last = fb.phase, now

    def end(self) -> None:
        if self.tty and self.phase is not None:
            self.stream.write("\r\x1b[K")
            self.stream.flush()


def validity_line(msg) -> str:
    """One ``~/validity`` message in words."""
    text = f"{msg.state_name}: {msg.samples} samples monitored"
    if msg.rms_ratio == msg.rms_ratio:  # not NaN
        text += f", residual RMS {msg.rms_ratio:.2f} x the identification's"
    if msg.whiteness_p == msg.whiteness_p:
        text += f", whiteness p {msg.whiteness_p:.2g}"
    return text + (f" -- {msg.reason}" if msg.reason else "")


def watch_validity(node: Node, topic: str, seconds: float, every: float = 1.0) -> int:
    """Print the model's validity (``~/validity``) for ``seconds``: each change, else once a second.

    For users without the ``ros2`` command line. Returns 0, or 2 when no message
    arrived at all (no node, or another ROS_DOMAIN_ID).
    """
    from collections import deque

    from spm_sysid_interfaces.msg import Validity

    got: deque = deque(maxlen=1)  # the latest message
    sub = node.create_subscription(Validity, topic, lambda m: got.append(m), LATCHED)
    last, tick = None, time.monotonic()
    try:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            rclpy.spin_once(node, timeout_sec=0.05)
            if not got:
                continue
            msg, now = got[-1], time.monotonic()
            # each change at once; else the latest, on a clock of its own (the node's
            # messages come about once a second too, and would drift against it)
            changed = msg.state_name != last
            if changed or now >= tick:
                print(validity_line(msg), flush=True)
                last = msg.state_name
                tick = now + every if changed else max(tick + every, now + 0.5 * every)
    except KeyboardInterrupt:
        pass
    finally:
        node.destroy_subscription(sub)
    if not got:
        print(f"error: nothing on {topic} within {seconds:.0f} s (is sysid_node running, with "
              "the same ROS_DOMAIN_ID?)", file=sys.stderr)
        return 2
    return 0


def main(action: str, node_name: str = "/spm_sysid", timeout: float = 300.0,
         show_model: bool = False, overrides: dict[str, str] | None = None,
         bag_path: str = "", trigger: bool = False, quiet: bool = False,
         as_json: bool = False) -> int:
    """Entry of ``spm-sysid call``; prints the answer, returns an exit status.

    0: identified (or cleared); 1: the node refused or the search failed; 2: no
    node or no answer; 130: canceled with Ctrl-C.
    """
    from rclpy.exceptions import NameValidationException
    from rclpy.validate_full_topic_name import validate_full_topic_name

    name = "/" + node_name.strip("/")
    try:
        validate_full_topic_name(f"{name}/{action}", is_service=True)
    except NameValidationException as exc:
        reason = str(exc).splitlines()[0].split(": ", 1)[-1].rstrip(":")
        print(f"error: --node {node_name!r} is not a valid ROS node name ({reason})",
              file=sys.stderr)
        return 2
    if (overrides or bag_path) and (trigger or action != "identify"):
        print("error: --set and --bag need the action (call identify without --trigger)",
              file=sys.stderr)
        return 2
    node_name = name
    from rclpy.signals import SignalHandlerOptions

    # Ctrl-C must reach us as KeyboardInterrupt (to cancel the goal), not shut ROS down
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = Node("spm_sysid_call")
    try:
        if action == "watch":
            return watch_validity(node, f"{node_name}/validity", timeout)
        if action == "identify" and not trigger:
            return _identify(node, f"{node_name}/identify", timeout, show_model,
                             overrides or {}, bag_path, quiet, as_json)
        ok, message = call_trigger(node, f"{node_name}/{action}", timeout)
        if ok:
            print("success: " + message)
        else:
            print("refused: " + message, file=sys.stderr)
        if ok and action == "identify" and show_model:
            doc = wait_for_model(node, f"{node_name}/model")
            if doc is not None:
                print(json.dumps(doc, indent=2) if as_json else model_summary(doc))
        return 0 if ok else 1
    except TimeoutError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    finally:
        node.destroy_node()
        rclpy.shutdown()


def _identify(node: Node, action: str, timeout: float, show_model: bool,
              overrides: dict[str, str], bag_path: str, quiet: bool,
              as_json: bool = False) -> int:
    from spm_sysid_interfaces.action import Identify

    line = None if quiet else FeedbackLine()
    try:
        out = identify_goal(node, action, overrides, bag_path, timeout, on_feedback=line)
    finally:
        if line is not None:
            line.end()
    r = out.result
    code = next((k for k, v in vars(Identify.Result).items()
                 if k.isupper() and v == r.error_code), str(r.error_code))
    if r.error_code in (Identify.Result.NONE, Identify.Result.DIVERGED):
        print("success: " + r.message)
        if show_model:
            doc = json.loads(r.document)
            print(json.dumps(doc, indent=2) if as_json else model_summary(doc))
        return 0
    if r.error_code == Identify.Result.CANCELED:
        print(f"canceled: {r.message}", file=sys.stderr)
        return 130 if out.interrupted else 1
    print(f"refused ({code}): {r.message}", file=sys.stderr)
    return 1
