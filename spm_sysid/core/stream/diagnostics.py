"""The node's /diagnostics statuses, built by pure functions from plain data.

The node turns :class:`Status` into ``diagnostic_msgs/msg/DiagnosticStatus``;
everything about what is reported, and how severe it is, lives here and is
tested without ROS.
"""

from __future__ import annotations

from dataclasses import dataclass, field

__all__ = ["ERROR", "OK", "WARN", "Status", "dashboard_status", "diagnostic_statuses",
           "online_status"]

OK, WARN, ERROR = 0, 1, 2


@dataclass(frozen=True)
class Status:
    """One status: level (OK, WARN, ERROR), name, message and key/value pairs."""

    level: int
    name: str
    message: str
    values: dict[str, str] = field(default_factory=dict)


def _values(values: dict) -> dict[str, str]:
    return {str(k): str(v) for k, v in values.items()}


def diagnostic_statuses(name: str, stats: dict, *, field_errors: int = 0,
                        unset_stamps: int = 0,
                        worker_ready: bool = True, worker_restarts: int = 0,
                        type_mismatches: list[str] | None = None, namesakes: int = 0,
                        running: tuple | None = None, last_error: str | None = None,
                        model: dict | None = None, restored_from: str | None = None,
                        callback_errors: int = 0, worker_failure: str = "",
                        unnamed: int = 0, ignored_parameters: list[str] | None = None
                        ) -> list[Status]:
    """The node's statuses: buffer, identification, one per correlation test.

    Parameters
    ----------
    name : str
        The node's name (prefix of every status name).
    stats : dict
        :meth:`spm_sysid.core.stream.buffer.SampleBuffer.stats_dict`.
    field_errors, unset_stamps, worker_ready, worker_restarts, type_mismatches
        The node's own health: messages whose field could not be read, messages
        with a zero header stamp (stamped on receipt instead), the worker process,
        publishers of another message type on a subscribed topic.
    namesakes : int
        Other nodes on the domain with this node's name (calls may reach them).
    running : tuple, optional
        ``(progress, seconds)`` of a running job: its last
        :class:`~spm_sysid.core.progress.Progress` and the seconds since it began.
    last_error : str, optional
        Why the last identification failed.
    model : dict, optional
        The last model document (its ``metadata`` has ``data`` and ``validation``).
    restored_from : str, optional
        Where the last model was loaded from at start-up.
    callback_errors : int
        Callbacks that raised and were logged (the node went on).
    worker_failure : str
        Why the worker process keeps dying while it starts ('' when it does not).
    unnamed, ignored_parameters
        Messages skipped that do not name a joint a field path asks for by name
        (another publisher's: counted, not a problem); parameters given at start
        that the node does not have (misspelled?).
    """
    health = {"field_errors": field_errors, "unset_stamps": unset_stamps,
              "namesakes": namesakes, "worker_ready": worker_ready,
              "worker_restarts": worker_restarts, "callback_errors": callback_errors,
              "type_mismatch": "; ".join(type_mismatches or []), "unnamed": unnamed,
              "ignored_parameters": ", ".join(ignored_parameters or [])}
    return [_buffer_status(name, stats, health, worker_failure),
            *_identification_statuses(name, running, last_error, model, restored_from)]


def _identification_statuses(name: str, running: tuple | None, last_error: str | None,
                             model: dict | None, restored_from: str | None) -> list[Status]:
    """A running job's status, the last failure, or the model's (one set per output)."""
    ident = f"{name}: identification"
    if running is not None:
        return [_running_status(ident, *running)]
    if last_error:
        return [Status(ERROR, ident, last_error)]
    if model is None:
        return []
    if model.get("schema") != "spm_sysid/narx-mimo-model":
        return _model_statuses(name, ident, model, restored_from)
    statuses = []
    for out, doc in zip(model["outputs"], model["models"]):  # several outputs
        statuses += _model_statuses(f"{name} ({out})", f"{ident} ({out})", doc, restored_from)
    for t in (model.get("metadata") or {}).get("cross_correlation_tests", []):
        statuses.append(Status(
            OK if t["passed"] else WARN, f"{name}: residual {t['name']}",
            ("inside the 95 % band" if t["passed"] else "outside the 95 % band")
            + f" ({t['fraction_inside']:.0%} of lags inside)", _values(t)))
    return statuses


def _buffer_status(name: str, stats: dict, health: dict, worker_failure: str) -> Status:
    """The buffer's counts and the node's own health, at the level of its worst problem."""
    lost = stats["rejected_nonfinite"] + stats["rejected_out_of_order"]
    problems = []
    if lost:
        problems.append(f"{lost} rejected")
    if stats.get("time_jumps"):
        problems.append(f"{stats['time_jumps']} jump(s) back in time")
    if health["type_mismatch"]:
        problems.append("a publisher of the wrong message type")
    if health["namesakes"]:
        problems.append(f"{health['namesakes']} other node(s) with this node's name")
    if health["unset_stamps"]:
        problems.append(f"{health['unset_stamps']} message(s) with header.stamp never set "
                        "(receive time used)")
    if not health["worker_ready"]:
        problems.append(f"worker not ready: {worker_failure}" if worker_failure
                        else "worker not ready")
    if health["callback_errors"]:
        problems.append(f"{health['callback_errors']} callback error(s) (see the log)")
    if health["ignored_parameters"]:
        problems.append(f"parameter(s) not of this node, ignored: "
                        f"{health['ignored_parameters']}")
    if health["unnamed"]:  # counted, but not a problem: not this node's joints
        problems.append(f"{health['unnamed']} message(s) skipped that do not name the joint(s) "
                        "asked for")
    level = OK
    if (lost or health["field_errors"] or health["unset_stamps"] or health["namesakes"]
            or stats.get("time_jumps") or not health["worker_ready"]
            or health["callback_errors"] or health["ignored_parameters"]):
        level = WARN
    if health["type_mismatch"] or worker_failure:
        level = ERROR
    return Status(level, f"{name}: buffer",
                  f"{stats['samples']} paired samples" + "".join(f", {p}" for p in problems),
                  {**_values(stats), **_values(health)})


def _running_status(ident: str, p, seconds: float) -> Status:
    """A running job: its phase and step, best value, evaluations, bound and seconds."""
    what = f"generation {p.step}" if p.phase == "search" else f"{p.phase} ({p.step})"
    return Status(OK, ident, f"running: {what}", _values(
        {"phase": p.phase, "step": p.step, "total": p.total, "best": f"{p.best:.4f}",
         "evaluations": p.evaluations, "bound": f"{p.bound:.4f}",
         "seconds": f"{seconds:.2f}"}))


def _model_statuses(name: str, ident: str, model: dict, restored_from: str | None
                    ) -> list[Status]:
    """The statuses of one (single-output) model document."""
    statuses: list[Status] = []
    meta = model.get("metadata") or {}
    data = meta.get("data") or {}
    incomplete = bool(data.get("gaps") or data.get("skipped_segments"))
    crit = model.get("criterion") or {}
    message = f"model with {len(model['terms'])} terms"
    if incomplete:
        message += f", fitted around {data['gaps']} gap(s) in the data"
    if restored_from:
        message += f", restored from {restored_from}"
    validation = meta.get("validation") or {}
    diverged = validation.get("diverged_at")
    level = WARN if incomplete else OK
    if diverged is not None:
        message += f"; its free-run simulation DIVERGED at sample {diverged}"
        level = ERROR
    cert = meta.get("certificate") or {}
    if cert.get("status") == "optimal":
        message += ", certified optimal"
    elif cert.get("status") == "limit":
        message += f", not certified (gap {cert.get('gap', float('nan')):.2f})"
    free = validation.get("free_run") or {}
    statuses.append(Status(level, ident, message, _values(
        {"criterion": crit.get("name"), "value": crit.get("value"),
         "mse": model.get("mse"), "focus": meta.get("focus", "prediction"),
         "free_run_fit_percent": free.get("fit_percent"), "diverged_at": diverged,
         "certificate": cert.get("status", "none"), "certificate_gap": cert.get("gap"),
         **{f"data_{k}": v for k, v in data.items()}})))
    warnings = meta.get("warnings") or []
    if warnings:
        statuses.append(Status(WARN, f"{name}: warnings",
                               f"{len(warnings)} warning(s): {warnings[0]}",
                               _values({f"warning_{i + 1}": w
                                        for i, w in enumerate(warnings)})))
    if validation.get("correlation_tests_skipped"):
        statuses.append(Status(WARN, f"{name}: correlation tests",
                               "not computed: " + validation["correlation_tests_skipped"]))
    for t in validation.get("correlation_tests", []):
        statuses.append(Status(
            OK if t["passed"] else WARN, f"{name}: correlation {t['name']}",
            ("inside the 95 % band" if t["passed"] else "outside the 95 % band")
            + f" ({t['fraction_inside']:.0%} of lags inside)", _values(t)))
    return statuses


def dashboard_status(name: str, url: str, requests: int, counts: dict) -> Status:
    """The live page's status: its address (never the token), requests, what was refused.

    ``counts``: connections refused over the cap, connection errors (timed out,
    reset), requests with a wrong token, requests whose Host is not the
    loopback's. Any of them makes the status WARN: somebody tried and was turned away.
    """
    turned_away = {k: v for k, v in counts.items() if v}
    message = f"serving {url}, {requests} request(s)"
    if turned_away:
        message += "; " + ", ".join(f"{v} {k.replace('_', ' ')}" for k, v in
                                    turned_away.items())
    return Status(WARN if turned_away else OK, f"{name}: dashboard", message,
                  _values({"url": url, "requests": requests, **counts}))


def online_status(name: str, session, auto: dict, ranges: dict | None = None) -> Status:
    """The ``model validity`` status: the monitor's state, its statistics, the counts.

    ``session`` is the node's :class:`~spm_sysid.core.online.session.OnlineSession`
    (None without a model, or with ``monitor`` off); ``auto`` counts the
    automatic re-identifications (``runs``, ``replaced``, ``kept``, ``failed``,
    ``last``); ``ranges``: the live samples beyond the model's fitted ranges
    (:meth:`~spm_sysid.core.validate.envelope.RangeWatch.values`).
    """
    values = {f"reidentify_{k}": v for k, v in auto.items()}
    values.update(ranges or {})
    if session is None:
        return Status(0, f"{name}: model validity", "no model monitored", _values(values))
    st = session.state
    level = {"VALID": 0, "DEGRADED": 1, "INVALID": 2}[st.state]
    change = session.change_stamp()
    values.update(session.stats())
    values.update({"state": st.state, "rms_ratio": st.rms_ratio,
                   "whiteness_p": st.whiteness_p, "cusum_mean": st.cusum_mean,
                   "cusum_variance": st.cusum_variance,
                   "change_stamp_ns": "" if change is None else change})
    message = st.state if not st.reason else f"{st.state}: {st.reason}"
    return Status(level, f"{name}: model validity", message, _values(values))
