"""The current model on its latched topics, saved first when ``model_path`` is set.

A model is published all or nothing: every message is built before the first
is sent (JSON document, coefficients, typed model and report, the set of
models of several outputs), and a model that could not be saved is not
published at all. A model saved by an earlier run is published again at
start-up. Whether a model has one output or several is decided once, by the
type of the model read from its document.
"""

from __future__ import annotations

import os

import numpy as np
from rclpy.node import Node
from spm_sysid_interfaces.msg import NarxModel as NarxModelMsg
from spm_sysid_interfaces.msg import NarxModelSet
from spm_sysid_interfaces.msg import ValidationReport as ValidationReportMsg
from std_msgs.msg import Float64MultiArray, MultiArrayDimension, String

from ...core.files import atomic_write_text, document_json
from ...core.model.mimo import MimoModel, read_model_document
from ..common import LATCHED
from ..typed import model_message, model_set_message, report_message

__all__ = ["ModelPublisher", "SaveFailedError", "model_size"]


class SaveFailedError(RuntimeError):
    """The model could not be saved to ``model_path`` (so nothing was published)."""


def model_size(model) -> str:
    """A model's size in words (one output, or several)."""
    if isinstance(model, MimoModel):
        return ", ".join(f"{o}: {len(m.terms)} terms" for o, m in zip(model.outputs,
                                                                      model.models))
    return f"{len(model.terms)} terms"


class ModelPublisher:
    """The model's latched topics of ``node`` and the model they carry.

    ``on_model(model, doc, residuals)`` is called with each model published
    (the online part starts its session).
    """

    def __init__(self, node: Node, on_model=None) -> None:
        self.node, self.on_model = node, on_model
        self.model_pub = node.create_publisher(String, "~/model", LATCHED)
        self.coef_pub = node.create_publisher(Float64MultiArray, "~/coefficients", LATCHED)
        self.resid_pub = node.create_publisher(Float64MultiArray, "~/residuals", LATCHED)
        self.narx_pub = node.create_publisher(NarxModelMsg, "~/narx_model", LATCHED)
        self.models_pub = node.create_publisher(NarxModelSet, "~/narx_models", LATCHED)
        self.report_pub = node.create_publisher(ValidationReportMsg, "~/validation", LATCHED)
        self.doc: dict | None = None  # the last model document published
        self.model = None  # ... as a NarxModel or MimoModel
        self.model_msg: NarxModelMsg | None = None
        self.report_msg: ValidationReportMsg | None = None
        self.models_msg: NarxModelSet | None = None
        self.restored_from: str | None = None

    def publish_result(self, result, model_path: str) -> None:
        """Save the model (when asked), then publish it: never publish what failed to save."""
        doc = result.model.to_dict()
        if model_path:
            try:
                atomic_write_text(model_path, document_json(doc) + "\n")
            except (OSError, ValueError) as exc:
                raise SaveFailedError(f"the model could not be saved to {model_path} ({exc}); "
                                      "nothing was published") from None
            self.node.get_logger().info(f"model saved to {model_path}")
        residuals = np.asarray(result.residuals, dtype=float)
        self.publish(result.model, doc, residuals)
        resid = Float64MultiArray(data=[float(e) for e in residuals.ravel()])
        if residuals.ndim == 2:  # several outputs: rows of samples, a column per output
            rows, cols = residuals.shape
            resid.layout.dim = [
                MultiArrayDimension(label="one_step_residuals", size=rows, stride=rows * cols),
                MultiArrayDimension(label="outputs: " + ",".join(doc["outputs"]), size=cols,
                                    stride=cols)]
        else:
            resid.layout.dim = [MultiArrayDimension(label="one_step_residuals",
                                                    size=len(resid.data),
                                                    stride=len(resid.data))]
        self.resid_pub.publish(resid)
        self.restored_from = None

    def publish(self, model, doc: dict, residuals=None) -> None:
        """The model on every latched topic: JSON, coefficients, typed model and report."""
        stamp = self.node.get_clock().now().to_msg()
        several = isinstance(model, MimoModel)
        # every message before publishing anything: all or nothing
        models_msg = model_set_message(doc, residuals, stamp)
        model_msg = None if several else model_message(doc, stamp)
        report_msg = None if several else report_message(doc, residuals, stamp)
        self.model_pub.publish(String(data=document_json(doc, indent=None)))
        parts = ([(f"{o}: ", m) for o, m in zip(doc["outputs"], doc["models"])] if several
                 else [("", doc)])
        terms = [f"{prefix}{t}" for prefix, m in parts for t in m["terms"]]
        coefs = Float64MultiArray(data=[float(c) for _, m in parts for c in m["coefficients"]])
        coefs.layout.dim = [MultiArrayDimension(label="terms: " + "; ".join(terms),
                                                size=len(terms), stride=len(terms))]
        self.coef_pub.publish(coefs)
        if not several:  # ~/narx_model and ~/validation carry one output's model
            self.narx_pub.publish(model_msg)
            self.report_pub.publish(report_msg)
        self.models_pub.publish(models_msg)
        self.doc, self.model = doc, model
        self.model_msg, self.report_msg, self.models_msg = model_msg, report_msg, models_msg
        if self.on_model is not None:
            self.on_model(model, doc, residuals)

    def republish_saved(self, path: str) -> None:
        """At start-up: publish the model saved by an earlier run again, latched.

        A file that holds no readable model (damaged, hand-edited, not JSON, numbers
        out of range, NaN anywhere) is reported and left alone; the node starts.
        """
        if not os.path.lexists(path):
            return
        try:
            model, doc = read_model_document(path)  # as saved, with its 'created' stamp
            self.publish(model, doc)
        except Exception as exc:  # noqa: BLE001 - whatever is in the file, the node starts
            self.node.get_logger().warning(f"model_path {path} holds no readable model "
                                           f"({exc}); nothing re-published")
            return
        self.restored_from = path
        self.node.get_logger().info(f"published the model saved in {path} "
                                    f"({model_size(model)}) again")

    def fill(self, answer) -> None:
        """The current model's messages and document into an action result or response."""
        if self.model_msg is not None:  # one output
            answer.model, answer.report = self.model_msg, self.report_msg
        answer.models = self.models_msg
        answer.document = document_json(self.doc, indent=None)
