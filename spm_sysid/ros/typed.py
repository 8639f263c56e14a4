"""The typed messages of ``spm_sysid_interfaces`` from a model document and progress.

The node publishes a model both as the JSON document (``~/model``, the contract
since the first version) and as ``spm_sysid_interfaces/msg/NarxModel``
(``~/narx_model``); the action's result and ``~/get_model`` carry the same
message with a ``ValidationReport``. Everything here is read from the model
document (docs/model_format.md), so a model restored from ``model_path`` gives
the same messages as a fresh one. NaN stands for "not known" in float fields,
-1 in ``diverged_at``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
from spm_sysid_interfaces.action import Identify
from spm_sysid_interfaces.msg import (
    CorrelationTest,
    FitMetrics,
    NarxModel,
    NarxModelSet,
    NarxTerm,
    Prediction,
    TermFactor,
    ValidationReport,
    Validity,
)

from ..core.model.terms import TermSpace
from ..core.progress import Progress

__all__ = ["feedback_message", "model_message", "model_set_message", "prediction_message",
           "report_message", "tracked_message", "validity_message"]

NAN = math.nan
_CERTIFICATION = {"optimal": NarxModel.CERTIFICATION_OPTIMAL,
                  "limit": NarxModel.CERTIFICATION_GAP}


def _num(value, default: float = NAN) -> float:
    return default if value is None else float(value)


def _uint(value) -> int:
    return 0 if value is None else max(int(value), 0)


def model_message(doc: Mapping, stamp=None) -> NarxModel:
    """``NarxModel`` from a model document (any readable version).

    ``stamp`` (a ``builtin_interfaces/Time``) goes into the header.
    """
    space = TermSpace.from_dict(doc["term_space"])
    meta = doc.get("metadata") or {}
    msg = NarxModel()
    if stamp is not None:
        msg.header.stamp = stamp
    msg.schema = str(doc.get("schema", ""))
    msg.document_version = int(doc.get("schema_version", 0))
    msg.output_name = space.output
    msg.input_names = list(space.inputs)
    msg.ny, msg.degree, msg.constant = space.ny, space.degree, bool(space.constant)
    msg.nu, msg.delay = [int(v) for v in space.nus], [int(v) for v in space.delays]
    msg.candidate_terms = space.n_terms
    msg.terms = [NarxTerm(name=name, index=int(i), factors=[
        TermFactor(signal=s, lag=int(lag), power=int(p)) for s, lag, p in space.term_factors(i)])
        for name, i in zip(doc["terms"], doc["term_indices"])]
    msg.coefficients = [float(c) for c in doc["coefficients"]]
    _fill_uncertainty(msg, doc.get("uncertainty"))
    crit = doc.get("criterion") or {}
    msg.criterion = str(crit.get("name") or "")
    msg.criterion_value = _num(crit.get("value"))
    msg.criterion_meaning = str(meta.get("criterion_meaning") or "")
    msg.focus = str(meta.get("focus") or "prediction")
    msg.selection = str((meta.get("selection") or {}).get("method") or "criterion")
    msg.one_step_mse = _num(doc.get("mse"))
    _fill_certificate(msg, meta.get("certificate") or {})
    data = meta.get("data") or {}
    msg.samples = _uint(data.get("samples", doc.get("n_samples")))
    msg.used_samples = _uint(data.get("used_samples", meta.get("samples_used")))
    msg.segments = _uint(data.get("used_segments", data.get("segments", 1)))
    msg.gaps = _uint(data.get("gaps"))
    msg.missing_samples = _uint(data.get("missing_samples"))
    msg.rejected_samples = _uint(data.get("rejected_samples"))
    _fill_validation(msg, meta.get("validation") or {})
    msg.warnings = [str(w) for w in meta.get("warnings") or []]
    return msg


def _fill_uncertainty(msg: NarxModel, unc: Mapping | None) -> None:
    """Standard errors and intervals (confidence level NaN when the document has none)."""
    msg.confidence_level = NAN
    if unc:
        msg.uncertainty_method = str(unc["method"])
        msg.confidence_level = float(unc["level"])
        msg.standard_errors = [float(v) for v in unc["standard_errors"]]
        msg.interval_lower = [float(a) for a, _ in unc["intervals"]]
        msg.interval_upper = [float(b) for _, b in unc["intervals"]]


def _fill_certificate(msg: NarxModel, cert: Mapping) -> None:
    """The certification's status, bound, gap and its account in words."""
    from ..core.search.certify import describe_certificate

    msg.certification = _CERTIFICATION.get(
        cert.get("status"), NarxModel.CERTIFICATION_NOT_CERTIFIABLE if cert
        else NarxModel.CERTIFICATION_NOT_RUN)
    msg.lower_bound = _num(cert.get("lower_bound"))
    msg.gap = _num(cert.get("gap"))
    msg.certificate = describe_certificate(cert) if cert else ""


def _fill_validation(msg: NarxModel, val: Mapping) -> None:
    """Fits (one-step, k-step, free run) and where the free run diverged (-1: never)."""
    msg.one_step_fit_percent = _num((val.get("one_step") or {}).get("fit_percent"))
    k_step = val.get("k_step") or {}
    msg.k_step_fit_percent = _num(k_step.get("fit_percent"))
    msg.k_step_horizon = _uint(k_step.get("horizon"))
    msg.free_run_fit_percent = _num((val.get("free_run") or {}).get("fit_percent"))
    diverged = val.get("diverged_at")
    msg.diverged = diverged is not None
    msg.diverged_at = -1 if diverged is None else int(diverged)


def _fit(metrics: Mapping | None) -> FitMetrics:
    out = FitMetrics(diverged_at=-1, mse=NAN, rmse=NAN, max_abs=NAN, mean_abs=NAN,
                     fit_percent=NAN)
    if not metrics:
        return out
    out.computed = True
    at = metrics.get("diverged_at")
    out.diverged, out.diverged_at = at is not None, -1 if at is None else int(at)
    for key in ("mse", "rmse", "max_abs", "mean_abs", "fit_percent"):
        setattr(out, key, _num(metrics.get(key)))
    return out


def report_message(doc: Mapping, residuals: np.ndarray | None = None,
                   stamp=None) -> ValidationReport:
    """``ValidationReport`` from the document's ``metadata.validation``.

    With the one-step ``residuals`` (a fresh identification) their statistics
    are computed; a restored model has only the RMS and largest value from the
    document (mean and standard deviation NaN).
    """
    val = (doc.get("metadata") or {}).get("validation") or {}
    msg = ValidationReport()
    if stamp is not None:
        msg.header.stamp = stamp
    msg.segment = str(val.get("segment") or "")
    msg.n_samples = _uint(val.get("n_samples"))
    msg.one_step = _fit(val.get("one_step"))
    msg.k_step = _fit(val.get("k_step"))
    msg.k_step_horizon = _uint((val.get("k_step") or {}).get("horizon"))
    msg.free_run = _fit(val.get("free_run"))
    msg.correlation_tests = _tests(val.get("correlation_tests"))
    msg.correlation_tests_skipped = str(val.get("correlation_tests_skipped") or
                                        ("" if val else "no validation in this model"))
    msg.correlation_tests_passed = bool(msg.correlation_tests) and all(
        t.passed for t in msg.correlation_tests)
    if residuals is not None and len(residuals):
        e = np.asarray(residuals, dtype=float)
        msg.residual_count = len(e)
        msg.residual_mean, msg.residual_std = float(np.mean(e)), float(np.std(e))
        msg.residual_rms = float(np.sqrt(np.mean(e * e)))
        msg.residual_max_abs = float(np.max(np.abs(e)))
    else:
        one = val.get("one_step") or {}
        msg.residual_count = msg.n_samples
        msg.residual_mean = msg.residual_std = NAN
        msg.residual_rms, msg.residual_max_abs = _num(one.get("rmse")), _num(one.get("max_abs"))
    return msg


def _tests(docs) -> list[CorrelationTest]:
    return [CorrelationTest(
        name=str(t["name"]), band=float(t["band"]), fraction_inside=float(t["fraction_inside"]),
        max_abs=_num(t.get("max_abs")), worst_lag=int(t.get("worst_lag") or 0),
        passed=bool(t["passed"])) for t in docs or []]


def model_set_message(doc: Mapping, residuals: np.ndarray | None = None,
                      stamp=None) -> NarxModelSet:
    """``NarxModelSet`` from a model document of one output or several.

    ``residuals``: one column per output (several), or the one output's.
    """
    msg = NarxModelSet()
    if stamp is not None:
        msg.header.stamp = stamp
    if doc.get("schema") == "spm_sysid/narx-mimo-model":
        docs = list(doc["models"])
        msg.output_names, msg.input_names = list(doc["outputs"]), list(doc["inputs"])
        res = None if residuals is None else np.asarray(residuals, dtype=float)
        cols = [None if res is None or res.ndim != 2 else res[:, i] for i in range(len(docs))]
        meta = doc.get("metadata") or {}
        msg.cross_correlation_tests = _tests(meta.get("cross_correlation_tests"))
        joint = meta.get("joint_criterion") or {}
        msg.joint_criterion_value = _num(joint.get("value"))
    else:
        docs, cols = [doc], [residuals]
        space = doc["term_space"]
        msg.output_names, msg.input_names = [str(space["output"])], list(space["inputs"])
        msg.joint_criterion_value = _num(doc.get("criterion_value"))
    msg.models = [model_message(d, stamp) for d in docs]
    msg.reports = [report_message(d, c, stamp) for d, c in zip(docs, cols)]
    msg.criterion = msg.models[0].criterion
    msg.cross_correlation_passed = all(t.passed for t in msg.cross_correlation_tests)
    return msg


def feedback_message(progress: Progress, elapsed: float) -> Identify.Feedback:
    """The action's feedback from a job's progress record."""
    return Identify.Feedback(
        phase=progress.phase, step=max(int(progress.step), 0),
        total=max(int(progress.total), 0), best_value=float(progress.best),
        structures_evaluated=max(int(progress.evaluations), 0),
        lower_bound=float(progress.bound), gap=float(progress.gap), elapsed=float(elapsed))


def _time(stamp_ns: int):
    from builtin_interfaces.msg import Time

    return Time(sec=int(stamp_ns // 1_000_000_000), nanosec=int(stamp_ns % 1_000_000_000))


def prediction_message(sample, horizon: int = 1, tracked: bool = False,
                       output_name: str = "") -> Prediction:
    """``Prediction`` of one :class:`~spm_sysid.core.online.session.OnlineSample`."""
    msg = Prediction(measured=sample.measured, predicted=sample.predicted,
                     residual=sample.residual, normalized_residual=sample.normalized,
                     tracked=tracked, predicted_k=sample.predicted_k,
                     output_name=output_name)
    msg.horizon = int(horizon)
    msg.header.stamp = _time(sample.stamp_ns)
    return msg


def validity_message(session, stamp_ns: int | None = None) -> Validity:
    """``Validity`` of the node's online session (NO_MODEL when there is none)."""
    msg = Validity(rms_ratio=NAN, whiteness_p=NAN, cusum_mean=NAN, cusum_variance=NAN)
    if stamp_ns is not None:
        msg.header.stamp = _time(stamp_ns)
    if session is None:
        msg.state, msg.state_name, msg.reason = Validity.NO_MODEL, "NO_MODEL", "no model"
        return msg
    st = session.state
    msg.state = getattr(Validity, st.state)
    msg.state_name, msg.reason, msg.samples = st.state, st.reason, st.samples
    msg.rms_ratio, msg.whiteness_p = st.rms_ratio, st.whiteness_p
    msg.cusum_mean, msg.cusum_variance = st.cusum_mean, st.cusum_variance
    change = session.change_stamp()
    msg.change_detected = change is not None
    if change is not None:
        msg.change_stamp = _time(change)
    msg.gaps, msg.transitions = session.gaps, len(session.transitions)
    sessions = getattr(session, "sessions", None)  # several outputs: each one's state
    if sessions is not None:
        msg.output_names = list(session.outputs)
        states = [s.state for s in sessions]
        msg.output_states = [int(getattr(Validity, s.state)) for s in states]
        msg.output_reasons = [s.reason for s in states]
    return msg


def tracked_message(doc: Mapping, tracker, stamp=None) -> NarxModel:
    """The identified model with the tracker's coefficients and covariance, marked tracked."""
    msg = model_message(doc, stamp)
    msg.coefficients = [float(c) for c in tracker.theta]
    se = tracker.standard_errors
    msg.uncertainty_method = "recursive least squares"
    msg.confidence_level = 0.95
    msg.standard_errors = [float(v) for v in se]
    msg.interval_lower = [float(c - 1.96 * e) for c, e in zip(tracker.theta, se)]
    msg.interval_upper = [float(c + 1.96 * e) for c, e in zip(tracker.theta, se)]
    msg.tracked, msg.tracked_updates = True, int(tracker.updates)
    return msg
