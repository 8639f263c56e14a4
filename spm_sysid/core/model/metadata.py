"""The model document's ``metadata``: every field the product reads, its type and range.

A model document is read by the command line (``validate``, the report), by the
node (its answer, ``/diagnostics``, the online monitor, the typed messages) and
by other programs. What a job writes is always well formed; a document edited by
hand or crafted is not. :func:`check_metadata` checks, once at load
(:meth:`~spm_sysid.core.model.narx.NarxModel.from_dict`), every field that
some part of the product reads, so that the readers behind it can take the
types for granted: a wrong type or a value out of range is a
:class:`~spm_sysid.core.errors.ModelFormatError` naming the field
(``metadata.orders.ny must be an integer >= 1, got 'abc'``), never a traceback
later nor a page that runs a script.

Fields the product does not read are kept as they are (a newer version's, a
user's own notes). Numbers are finite; where a job may have no number (a
diverged run, a scan that failed) the document holds ``null``
(:func:`spm_sysid.core.files.json_ready`).
"""

from __future__ import annotations

import math
from collections.abc import Callable

from ..errors import ModelFormatError

__all__ = ["check_metadata", "check_mimo_metadata", "check_monitor"]

Check = Callable[[object, str], None]


def _fail(path: str, wants: str, value) -> None:
    shown = repr(value)
    if len(shown) > 60:
        shown = shown[:57] + "..."
    raise ModelFormatError(f"{path} must be {wants}, got {shown}")


def _is_number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def number(low: float = -math.inf, high: float = math.inf, null: bool = True) -> Check:
    """A finite number in [low, high] (or null when ``null``)."""
    if low > -math.inf and high < math.inf:
        wants = f"a number from {low:g} to {high:g}"
    elif low > -math.inf:
        wants = f"a number >= {low:g}"
    else:
        wants = "a finite number"

    def check(value, path: str) -> None:
        if value is None and null:
            return
        if not _is_number(value) or not low <= value <= high:
            _fail(path, wants + (" or null" if null else ""), value)
    return check


def integer(low: int = 0, null: bool = True) -> Check:
    """An integer >= low (or null when ``null``); true and false are not integers."""
    def check(value, path: str) -> None:
        if value is None and null:
            return
        if isinstance(value, bool) or not isinstance(value, int) or value < low:
            _fail(path, f"an integer >= {low}" + (" or null" if null else ""), value)
    return check


def text(null: bool = True, choices: tuple[str, ...] = ()) -> Check:
    """Text (one of ``choices`` when given)."""
    def check(value, path: str) -> None:
        if value is None and null:
            return
        if not isinstance(value, str) or (choices and value not in choices):
            _fail(path, ("one of " + ", ".join(repr(c) for c in choices)) if choices
                  else "text", value)
    return check


def flag(value, path: str) -> None:
    """True or false."""
    if not isinstance(value, bool):
        _fail(path, "true or false", value)


def items(each: Check, null: bool = True) -> Check:
    """A list whose every item passes ``each``."""
    def check(value, path: str) -> None:
        if value is None and null:
            return
        if not isinstance(value, list):
            _fail(path, "a list", value)
        for i, v in enumerate(value):
            each(v, f"{path}[{i}]")
    return check


def mapping(each: Check) -> Check:
    """An object of text keys whose every value passes ``each``."""
    def check(value, path: str) -> None:
        if value is None:
            return
        if not isinstance(value, dict):
            _fail(path, "an object", value)
        for k, v in value.items():
            each(v, f"{path}.{k}")
    return check


def row(*cells: Check) -> Check:
    """A list of fixed length, one check per cell."""
    def check(value, path: str) -> None:
        if not isinstance(value, list) or len(value) != len(cells):
            _fail(path, f"a list of {len(cells)} values", value)
        for i, (c, v) in enumerate(zip(cells, value)):
            c(v, f"{path}[{i}]")
    return check


def fields(spec: dict[str, Check], required: tuple[str, ...] = ()) -> Check:
    """An object whose known fields pass their checks (others kept unread)."""
    def check(value, path: str) -> None:
        if value is None:
            return
        if not isinstance(value, dict):
            _fail(path, "an object", value)
        for key in required:
            if key not in value:
                raise ModelFormatError(f"{path} has no {key!r}")
        for key, c in spec.items():
            if key in value:
                c(value[key], f"{path}.{key}")
    return check


def check_monitor(doc, path: str = "monitor") -> dict:
    """The online monitor's reference (``metadata.monitor``): types, and values it can hold.

    Each maximum is checked against the largest value that ``samples`` residuals
    can give at all (a window's RMS ratio at most sqrt(samples / window), a
    window's Ljung-Box Q at most w(w+2)(1 + 1/2 + ... + 1/(w-1)), the CUSUM
    statistics at most ``samples``): a reference beyond those was not computed
    from residuals, and a monitor given it would call anything VALID.

    Raises
    ------
    ModelFormatError
        Naming the field (``metadata.monitor.sigma must be ...``).
    """
    fields({"version": integer(1, null=False), "samples": integer(2, null=False),
            "sigma": number(0.0, null=False), "innovation_sd": number(0.0, null=False),
            "whitening_ar": items(number(null=False), null=False),
            "cusum_mean_max": number(0.0, null=False),
            "cusum_variance_max": number(0.0, null=False),
            "windows": items(fields({"window": integer(2, null=False),
                                     "ljung_box_max": number(0.0, null=False),
                                     "rms_ratio_max": number(0.0, null=False)},
                                    required=("window", "ljung_box_max", "rms_ratio_max")),
                             null=False),
            "input_std": number(0.0)},
           required=("version", "samples", "sigma", "innovation_sd", "whitening_ar",
                     "cusum_mean_max", "cusum_variance_max", "windows"))(doc, path)
    if doc is None:
        return doc
    n = doc["samples"]
    for key in ("sigma", "innovation_sd"):
        if not doc[key] > 0:
            _fail(f"{path}.{key}", "a number > 0", doc[key])
    if len(doc["whitening_ar"]) > 100:
        _fail(f"{path}.whitening_ar", "a list of at most 100 numbers", doc["whitening_ar"])
    for key in ("cusum_mean_max", "cusum_variance_max"):
        if doc[key] > n:
            _fail(f"{path}.{key}", f"at most {n} (what {n} residuals can give)", doc[key])
    for i, w in enumerate(doc["windows"]):
        size, where = w["window"], f"{path}.windows[{i}]"
        top = math.sqrt(n / size) * (1 + 1e-9)
        if w["rms_ratio_max"] > top:
            _fail(f"{where}.rms_ratio_max", f"at most {top:.4g} (the largest RMS ratio "
                  f"{n} residuals can give in a window of {size})", w["rms_ratio_max"])
        q = size * (size + 2) * sum(1.0 / k for k in range(1, size)) * (1 + 1e-9)
        if w["ljung_box_max"] > q:
            _fail(f"{where}.ljung_box_max", f"at most {q:.4g} (the largest Ljung-Box Q of a "
                  f"window of {size})", w["ljung_box_max"])
    return doc


MSE = number(0.0)

#: A certificate's fields, and those its status needs (the sentence that describes it).
CERTIFICATE = fields({
    "status": text(null=False, choices=("optimal", "limit", "refused")),
    "reason": text(), "nodes": integer(), "seconds": number(0.0), "value": number(),
    "lower_bound": number(), "gap": number(0.0), "ga_value": number(),
    "warm_start": number(), "one_step_mse": MSE, "mse_lower_bound": MSE,
    "size": integer(), "terms": items(text(null=False))}, required=("status",))
CERTIFICATE_NEEDS = {"optimal": ("nodes", "seconds", "value"),
                     "limit": ("reason", "lower_bound", "gap", "value"),
                     "refused": ("reason",)}


def _certificate(value, path: str) -> None:
    CERTIFICATE(value, path)
    if value is not None:
        for key in CERTIFICATE_NEEDS[value["status"]]:
            if value.get(key) is None:
                raise ModelFormatError(f"{path} of status {value['status']!r} has no {key!r}")


FRACTION = number(0.0, 1.0, null=False)

#: One correlation test (``validation.correlation_tests``, ``cross_correlation_tests``).
TEST = fields({"name": text(null=False), "passed": flag, "fraction_inside": FRACTION,
               "band": number(0.0, null=False), "max_abs": number(0.0),
               "worst_lag": integer(-10**9), "label": text()},
              required=("name", "passed", "fraction_inside", "band"))

#: One kind of prediction's errors (``validation.one_step`` ...).
METRICS = fields({"mse": MSE, "rmse": MSE, "max_abs": MSE, "mean_abs": MSE,
                  "fit_percent": number(), "diverged_at": integer(), "horizon": integer(1)})

def _count_or_text(value, path: str) -> None:
    """A data account's entry: a count, a number (the period), text (its source) or null."""
    if value is None or isinstance(value, str) or (_is_number(value) and value >= 0):
        return
    _fail(path, "a number >= 0, text or null", value)


#: The data account (``metadata.data``).
DATA = mapping(_count_or_text)

#: How the identification's record was decimated (validate and the monitor repeat it).
DECIMATION = fields({"factor": integer(1, null=False), "samples": integer(),
                     "kept": integer(), "unused": integer(), "inputs": text(),
                     "outputs": text()}, required=("factor",))

#: The output spikes left out of the identification's segments (``--spikes gaps``).
SPIKES = fields({"spikes": integer(), "samples": integer(), "at": items(integer())})

#: The topics, fields and names the signals were read from (a bag, the node; ``validate --bag``).
TOPICS = fields({k: text() for k in ("input_topic", "input_field", "input_names",
                                          "output_topic", "output_field", "output_names",
                                          "stamp_tolerance")})

def _interval(value, path: str) -> None:
    """A signal's fitted range: [low, high], finite, low <= high."""
    row(number(null=False), number(null=False))(value, path)
    if value[0] > value[1]:
        _fail(path, "[low, high] with low <= high", value)


#: Each signal's smallest and largest value on the estimation samples (validate names
#: new data beyond them: spm_sysid.core.validate.envelope).
RANGES = fields({"inputs": mapping(_interval), "outputs": mapping(_interval)})

#: Every field of ``metadata`` that the product reads.
METADATA = fields({
    "focus": text(choices=("prediction", "simulation")),
    "warnings": items(text(null=False)),
    "criterion_meaning": text(),
    "seed": integer(),
    "selection": fields({
        "method": text(null=False), "note": text(), "what": text(null=False),
        "folds": integer(), "held_out_mse": MSE, "held_out_stderr": MSE, "ratio": MSE,
        "in_sample_mse": MSE, "removed_by_guard": integer(), "candidates": integer(),
        "left_range_held_out": integer(),
        "linear_or_nonlinear": fields({
            "choice": text(choices=("linear", "nonlinear")), "ratio": MSE,
            "p_value": number(0.0, 1.0), "best_linear_held_out_mse": MSE,
            "best_linear_held_out_stderr": MSE, "blocks": integer(),
            "tested": text(choices=("linear", "nonlinear")), "terms": integer(),
            "nonlinear_terms": integer(), "challenger_fate": text(),
            "shrunk_nonlinear_terms": number(0.0, 1.0), "fallback": text(),
            "linear_arx_order": integer(1), "linear_arx_held_out_mse": MSE,
            "linear_arx_held_out_stderr": MSE})},
        required=("method", "what", "folds")),
    "certificate": lambda v, p: _certificate(v, p),
    "orders": fields({
        "ny": integer(1, null=False), "nu": integer(1), "degree": integer(1, null=False),
        "reason": text(), "criterion": text(), "samples": integer(),
        "order_scan": items(row(integer(1, null=False), number())),
        "degree_scan": items(items(number())), "space_scan": items(items(number())),
        "focus": text(choices=("prediction", "simulation")), "max_terms": integer(),
        "constant": flag},
        required=("ny", "degree")),
    "data_check": fields({
        "rows": integer(null=False), "usable": integer(null=False),
        "candidates": integer(null=False), "rows_per_candidate": number(0.0, null=False),
        "excitation_order": mapping(integer()), "lags": mapping(integer()),
        "condition": number(0.0)},
        required=("rows", "usable", "candidates", "rows_per_candidate")),
    "polish": fields({"ga_value": number(), "value": number(), "steps": integer(),
                      "restart": fields({"first": number(), "second": number(),
                                         "forward": number(), "all_terms": number(),
                                         "common": number(), "kept": text()})}),
    "data": DATA,
    "samples_used": integer(),
    "validation": fields({
        "segment": text(), "n_samples": integer(), "diverged_at": integer(),
        "one_step": METRICS, "k_step": METRICS, "free_run": METRICS,
        "correlation_tests_skipped": text(), "correlation_tests": items(TEST)}),
    "monitor": lambda v, p: check_monitor(v, p),
    "interrupted": fields({"phase": text(), "model": text()}),
    "decimation": DECIMATION,
    "spikes": SPIKES,
    "topics": TOPICS,
    "ranges": RANGES,
    "operating_point": fields({
        "output": mapping(number(null=False)), "inputs": mapping(number(null=False)),
        "reason": text(null=False), "selected_terms": items(text(null=False)),
        "terms_added": integer()},
        required=("reason",)),
})

#: The several-output document's own metadata (each output's model has its own).
MIMO_METADATA = fields({"cross_correlation_tests": items(TEST),
                        "joint_criterion": fields({"value": number(), "name": text()}),
                        "warnings": items(text(null=False)), "data": DATA,
                        "decimation": DECIMATION, "spikes": SPIKES,
                        "topics": TOPICS, "ranges": RANGES})


def check_metadata(metadata, path: str = "metadata") -> dict:
    """Check a single-output model's metadata (see the module doc); returns it.

    Raises
    ------
    ModelFormatError
        A field the product reads has a wrong type or a value out of range.
    """
    if not isinstance(metadata, dict):
        _fail(path, "an object", metadata)
    METADATA(metadata, path)
    return metadata


def check_mimo_metadata(metadata, path: str = "metadata") -> dict:
    """Check a several-output document's own metadata; returns it."""
    if not isinstance(metadata, dict):
        _fail(path, "an object", metadata)
    MIMO_METADATA(metadata, path)
    return metadata
