"""The job of a record with several outputs: one coupled model, validated per output.

:func:`spm_sysid.core.jobs.run.run_job` hands a record of several outputs here.
Each output is one single-output job
(:func:`~spm_sysid.core.jobs.single.run_single_job`) on the record seen from that
output -- the inputs, then the other outputs as extra signals with delay 1
(:func:`spm_sysid.core.model.mimo.output_space`) -- so every output gets the whole
single-output path: segments, GA with SPM, polish, certification, validated
selection, uncertainty, warnings and the correlation tests of its residuals.
Then the outputs are put together (:class:`~spm_sysid.core.model.mimo.MimoModel`)
and validated jointly:

* the free-run simulation in each output's report is replaced by the **coupled**
  one (every output's simulated value fed back into every term that uses it),
  segment by segment, and so is the k-step prediction (with a horizon); the
  single-output free-run band (other outputs measured) is left out, since it
  would not describe the coupled run;
* with simulation focus, the coefficients of all outputs are refined jointly on
  the coupled free-run error (:func:`spm_sysid.core.fit.refine_coupled.refine_coupled`)
  and each output validated again with them;
* the one-step residuals of every pair of outputs are cross-correlated
  (``cross_<a>_<b>``, lags -L..L without lag 0: correlated noise at the same
  instant is not a model error, a correlation at another lag is a missed
  coupling).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from ..defaults import PARALLEL_OUTPUT_BYTES
from ..model.mimo import MimoModel, augmented_inputs, in_threads, output_space
from ..model.operating_point import OperatingPoint, in_deviations, in_record_units
from ..online.monitor import store_monitor_reference
from ..progress import Progress, ProgressFn
from ..record import Record
from ..select.coupled import select_coupled
from ..validate.correlation import CorrelationTest, ccf
from ..validate.envelope import data_ranges
from ..validate.explained import set_explained_warning
from ..validate.validation import validate_model
from .single import choose_orders, run_single_job, validation_segments

__all__ = ["MimoJobResult", "couple_reports", "coupled_rows", "cross_correlation_tests",
           "cross_summary", "describe_coupled", "run_mimo_job"]


@dataclass
class MimoJobResult:
    """What a job on several outputs produced.

    Attributes
    ----------
    model : MimoModel
        The coupled model; its metadata has the data account, the validation
        per output and the cross-correlation tests.
    outputs : list of JobResult
        Each output's own job (its model is ``model.models[i]``; its report's
        free run is the coupled one).
    cross_tests : list of CorrelationTest
        The residuals' cross-correlation between every pair of outputs.
    data : dict
        The data account (as a single-output job gives it).
    seconds : dict
        ``total`` and per output.
    times : ndarray or None
        Seconds of the reports' rows (from the record's stamps), as the job chose
        them; None without stamps or validation.
    """

    model: MimoModel
    outputs: list
    cross_tests: list[CorrelationTest]
    data: dict
    seconds: dict = field(default_factory=dict)
    times: np.ndarray | None = None

    @property
    def output_names(self) -> tuple[str, ...]:
        return self.model.outputs

    @property
    def report(self):
        """None: each output has its report (``outputs[i].report``)."""
        return None

    @property
    def per_output(self) -> list:
        """Each output's name, model, report and search history (as a job of one gives it)."""
        from .single import OutputResult

        return [OutputResult(name, r.model, r.report, r.search.history)
                for name, r in zip(self.output_names, self.outputs)]

    @property
    def diverged(self) -> list[str]:
        """Outputs whose coupled free-run simulation left their measured range."""
        return [name for name, r in zip(self.output_names, self.outputs)
                if r.report is not None and r.report.diverged_at is not None]

    @property
    def residuals(self) -> np.ndarray:
        """One-step residuals, one column per output (rows of the validation data)."""
        cols = [r.residuals for r in self.outputs]
        n = min(len(c) for c in cols)
        return np.column_stack([c[len(c) - n:] for c in cols]) if n else np.empty((0, 0))

    @property
    def criterion_value(self) -> float:
        """The joint summary: the sum of the outputs' criterion values."""
        return float(sum(r.model.criterion_value for r in self.outputs))

    def summary(self, style: str = "lines") -> str:
        """``"line"``: one paragraph per output joined; ``"lines"``: a block per output."""
        crit = self.outputs[0].model.criterion.upper()
        joint = (f"joint {crit} (sum over the outputs) = {self.criterion_value:.2f}, "
                 f"{self.seconds.get('total', 0.0):.2f} s")
        failed = [t.name for t in self.cross_tests if not t.passed]
        cross = ("" if not self.cross_tests else
                 "residual cross-correlation between outputs: " + (
                     "inside the band" if not failed else "outside the band: "
                     + ", ".join(failed)))
        sel = self.model.metadata.get("coupled_selection") or {}
        first = (f"WARNING: {sel['all_diverge']}; the outputs' own choices are returned and "
                 "do not simulate coupled" if sel.get("all_diverge") else "")
        if style == "line":
            parts = [f"{name}: {r.summary('line')}" for name, r in
                     zip(self.output_names, self.outputs)]
            coupled = describe_coupled(sel)
            return ((f"{first} || " if first else "") + " || ".join(parts) + f" || {joint}"
                    + (f", {coupled}" if coupled and not first else "")
                    + (f", {cross}" if cross else ""))
        blocks = [first] if first else []
        for name, r in zip(self.output_names, self.outputs):
            text = r.summary("lines").replace("\n  free-run:", "\n  coupled free-run:")
            blocks.append(f"== output {name} ==\n{text}")
        refined = self.model.metadata.get("coupled_refinement")
        if refined:
            blocks.append(
                "the outputs' coefficients refined jointly on the coupled free-run error "
                f"({refined['evaluations']} runs): normalised SSE "
                f"{refined['before']:.4g} -> {refined['after']:.4g}" if refined["taken"] else
                f"joint refinement not taken ({refined.get('message')})")
        coupled = describe_coupled(self.model.metadata.get("coupled_selection"))
        if coupled:
            blocks.append(coupled)
        blocks.append(joint)
        if self.cross_tests:
            blocks.append(cross_summary(self.cross_tests))
        return "\n".join(blocks)


def describe_coupled(doc: dict | None) -> str:
    """The coupled judgement in a sentence ('' when there is none)."""
    if not doc or doc.get("all_diverge") or "chosen" not in doc:
        return ""
    text = (f"coupled judgement on {doc['folds']} held-out blocks: {doc['chosen']} "
            f"({doc['fitted']})")
    if doc.get("p_value") is not None:
        verdict = ("better than the best linear by more than the noise"
                   if doc.get("choice") == "nonlinear" else
                   "not better than the best linear by more than the noise")
        text += (f"; the best nonlinear finalist's coupled error is {doc['ratio']:.2f}x the "
                 f"best linear's (p = {doc['p_value']:.3g}): {verdict}")
    arx = _least_squares_arx(doc.get("finalists") or [])
    if arx is not None:
        text += (f"; the {arx['name']} (least squares) had coupled error "
                 f"{arx['held_out_error']:.4g} on the same blocks")
    removed = doc.get("removed_by_guard") or []
    if removed:
        text += (f"; {len(removed)} finalist(s) removed because their coupled run diverged "
                 "when driven by the guard's inputs")
        if doc.get("choice") == "nonlinear" and doc.get("nonlinear") and \
                doc["chosen"] != doc["nonlinear"]:
            text += f" ({doc['nonlinear']} among them: the model returned is the next finalist)"
    return text


def _least_squares_arx(finalists: list[dict]) -> dict | None:
    """The coupled finalists' yardstick: the least-squares linear MIMO ARX of lowest error.

    None when no such finalist simulated every held-out block.
    """
    rows = [f for f in finalists if str(f.get("name", "")).startswith("linear MIMO ARX")
            and f.get("fitted") == "least squares"
            and isinstance(f.get("held_out_error"), (int, float))
            and np.isfinite(f["held_out_error"])]
    return min(rows, key=lambda f: f["held_out_error"]) if rows else None


def cross_correlation_tests(residuals: np.ndarray, names: tuple[str, ...],
                            max_lag: int = 20) -> list[CorrelationTest]:
    """``corr(e_a(t), e_b(t - tau))`` for every pair a < b of outputs, tau = -L..L.

    Lag 0 is shown but not checked (see the module docstring).
    """
    e = np.asarray(residuals, dtype=float)
    if e.ndim != 2 or len(e) <= max_lag or not np.all(np.isfinite(e)):
        return []
    e = e / np.where(np.max(np.abs(e), axis=0) > 0, np.max(np.abs(e), axis=0), 1.0)
    band = 1.96 / np.sqrt(len(e))
    sym = np.arange(-max_lag, max_lag + 1)
    out = []
    for a in range(e.shape[1]):
        for b in range(a + 1, e.shape[1]):
            out.append(CorrelationTest(f"cross_{names[a]}_{names[b]}", sym,
                                       ccf(e[:, a], e[:, b], sym), band))
    return out


def _per_segment(run, lag: int, u: np.ndarray, Y: np.ndarray,
                 segments: list[tuple[int, int]]) -> tuple[np.ndarray, list[int | None]]:
    """``run(u, Y) -> (rows, diverged)`` on every segment from its own start, joined.

    Rows after each segment's first ``lag`` samples; per output the first sample
    (record index) where a run diverged, or None.
    """
    runs, diverged = [], [None] * Y.shape[1]
    for a, b in segments:
        if b - a <= lag:
            continue
        rows, div = run(u[a:b], Y[a:b])
        runs.append(rows)
        for i, d in enumerate(div):
            if d is not None and diverged[i] is None:
                diverged[i] = a + d
    return np.concatenate(runs), diverged


def coupled_rows(model: MimoModel, i: int, segments: list[tuple[int, int]]
                 ) -> list[tuple[int, int]]:
    """Output ``i``'s validation segments: from the coupled run's first row of each.

    With ``orders: auto`` each output has its own space; one whose largest lag is
    below the coupled model's starts each segment that much later, so that every
    output's report has the coupled run's rows (its residuals line up with the
    others' for the cross-correlation tests).
    """
    lag = model.max_lag
    shift = lag - model.models[i].term_space.max_lag
    return [(a + shift, b) for a, b in segments if b - a > lag]


def couple_reports(model: MimoModel, u: np.ndarray, Y: np.ndarray,
                   segments: list[tuple[int, int]], reports: list,
                   correlation_lags: int = 20) -> list[CorrelationTest]:
    """Make each output's validation report the coupled model's; the cross tests.

    ``reports`` (one per output, each validated on ``segments`` with the other
    outputs measured) get the coupled free run instead of their own (and no
    single-output free-run band); the residuals' cross-correlation tests are
    returned.
    """
    free, diverged = _per_segment(model.simulate, model.max_lag, u, Y, segments)
    horizon = next((r.horizon for r in reports if r is not None and r.horizon), None)
    kstep = (_per_segment(lambda u_, Y_: model.k_step(u_, Y_, horizon), model.max_lag, u, Y,
                          segments) if horizon else None)
    for i, rep in enumerate(reports):
        if rep is None or len(rep.measured) != len(free):
            continue
        m = rep.score(free[:, i], diverged[i])
        rep.free_run, rep.free_run_metrics, rep.free_run_band = free[:, i], m, None
        if kstep is not None and rep.k_step is not None:
            rep.k_step = kstep[0][:, i]
            rep.k_step_metrics = rep.score(rep.k_step, kstep[1][i])
        if m["diverged_at"] is not None:
            rep.tests_skipped = (f"the coupled free-run simulation diverged at sample "
                                 f"{m['diverged_at']}: the model does not describe the system")
            rep.tests = []
    if any(r is None for r in reports):
        return []
    resid = np.column_stack([r.residuals for r in reports])
    return cross_correlation_tests(resid, tuple(model.outputs), correlation_lags)


def cross_summary(tests: list[CorrelationTest]) -> str:
    """The cross-correlation tests in a few lines ('' when there are none)."""
    if not tests:
        return ""
    lines = [f"cross-correlation of the outputs' residuals (95 % band ±{tests[0].band:.4f}, "
             "lag 0 not checked):"]
    for t in tests:
        state = "OK  " if t.passed else "WARN"
        lines.append(f"    {state} {t.name:<16} {t.fraction_inside:6.1%} of lags inside, "
                     f"worst at lag {t.worst_lag}")
    return "\n".join(lines)


def _view(record: Record, space, names, i: int) -> Record:
    """The record seen from output ``i``: the inputs, then the other outputs as inputs."""
    return replace(record, u=augmented_inputs(record.u, record.y, i), y=record.y[:, i],
                   output_name=names[i], output_names=(names[i],), input_names=space.inputs,
                   fed_back=tuple(n for j, n in enumerate(names) if j != i))


def _choose_mimo_orders(record: Record, base) -> tuple[Any, dict, list]:
    """``orders: auto`` for several outputs: each output in the space it proposes.

    Each output is seen with the inputs and the other outputs as inputs
    (:func:`~spm_sysid.core.jobs.single.choose_orders` on that view) and searched
    in its own proposal (order for its own lags, the inputs' and the other
    outputs', and degree), within the scan's budget of terms. The settings
    returned hold the largest order and degree (the document's ``ny``, ``nu``,
    ``degree``; the regressor presets' lags); the coupled judgement's linear MIMO
    ARX finalists go up to the largest order
    (:func:`~spm_sysid.core.select.coupled.linear_mimo`). Returns the settings,
    the document's ``orders`` and each output's space.
    """
    names = tuple(record.output_names)
    est, _, _ = validation_segments(record, base)
    per = {}
    for i, name in enumerate(names):
        space = output_space(base.term_space, names, i)
        _, why = choose_orders(_view(record, space, names, i),
                               replace(base, term_space=space), est)
        per[name] = why
    n = max(w["ny"] for w in per.values())
    d = max(w["degree"] for w in per.values())
    chosen = replace(base.term_space, ny=n, nu=n, degree=d)
    spaces = [replace(base.term_space, ny=w["ny"], nu=w["ny"], degree=w["degree"])
              for w in per.values()]
    doc = {"mode": "auto", "ny": n, "nu": n, "degree": d,
           "reason": "each output in its own proposal: " + "; ".join(
               f"{k}: order {w['ny']}, degree {w['degree']}" for k, w in per.items())
           + f" (the linear MIMO ARX finalists up to order {n})",
           "per_output": per}
    return replace(base, term_space=chosen, orders="given"), doc, spaces


def _with_regressors(record: Record, base):
    """Regressors for several outputs: presets expanded for every output, each read causally.

    ``friction`` gives every output's model the friction bases of every output
    (through the coupling a joint feels the other joints' friction), each scaled
    from that output's estimation samples; ``saturation`` clips the record's
    inputs at the level each output's linear ARX prefers (one set per output).
    An expression may read another output at t-1 or earlier only: the coupled
    simulation steps all outputs together.

    Raises
    ------
    SettingsError
        An expression outside the grammar, naming an unknown signal, or reading
        another output at t.
    """
    from ..errors import SettingsError
    from ..model.presets import expand_presets, preset_inputs
    from ..model.regressors import RegressorError, parse

    items = [t.strip() for t in base.regressors.split(";") if t.strip()]
    if not items:
        return base
    names = tuple(record.output_names)
    est, _, _ = validation_segments(record, base)
    texts: list[str] = []
    for item in items:
        if item in ("friction", "saturation"):
            u = preset_inputs(base.term_space, np.concatenate([record.u[a:b] for a, b in est]))
            for i, name in enumerate(names):
                y = np.concatenate([record.y[a:b, i] for a, b in est])
                texts += expand_presets([item], name, y, u, base.term_space.ny)
        else:
            texts.append(item)
    for i, name in enumerate(names):
        inputs = output_space(base.term_space, names, i).inputs
        for text in texts:
            try:
                signals = parse(text, name, inputs).signals()
            except RegressorError as exc:
                raise SettingsError(f"regressors: {exc}") from None
            now = sorted(s for s, lag in signals if s in names and s != name and lag < 1)
            if now:
                raise SettingsError(f"regressors: {text!r} reads {now[0]}(t), an output "
                                    f"that is stepped with {name}; use {now[0]}(t-1) or "
                                    "earlier")
    return replace(base, regressors="; ".join(dict.fromkeys(texts)))


def _outputs_at_once(record: Record, base, spaces: list) -> int:
    """How many outputs identify side by side: their working memory within a budget.

    Each output's job holds its candidate matrix (estimation rows x its terms) and
    the slices its fits work on (:func:`~spm_sysid.core.fit.problem.working_bytes`);
    :data:`~spm_sysid.core.defaults.PARALLEL_OUTPUT_BYTES` bounds their sum, so the
    outputs of a long record take turns instead of doubling the peak memory. At
    least one.
    """
    from ..fit.problem import working_bytes

    names = tuple(record.output_names)
    est, _, _ = validation_segments(record, base)
    largest = 0
    for i in range(len(names)):
        space = output_space(spaces[i], names, i)
        rows = sum(max(b - a - space.max_lag, 0) for a, b in est)
        largest = max(largest, working_bytes(rows, space.n_terms))
    return int(min(len(names), max(1, PARALLEL_OUTPUT_BYTES // max(largest, 1))))


def run_mimo_job(record: Record, settings, *, progress: ProgressFn | None = None,
                 progress_every: int = 25, metadata: Mapping[str, Any] | None = None
                 ) -> MimoJobResult:
    """Identify and validate a record of several outputs (see the module doc).

    Parameters and errors as for :func:`~spm_sysid.core.jobs.single.run_single_job`.
    """
    t0 = time.perf_counter()
    names = tuple(record.output_names)
    clash = set(names) & set(record.input_names)
    if clash:
        from ..errors import DataError
        raise DataError(f"an output and an input share a name: {', '.join(sorted(clash))} "
                        "(set output_names or input_names)")
    Y, u = record.y, record.u
    base = settings.for_signals(record.input_names, names[0])
    lock = threading.Lock()

    def relay(p: Progress) -> None:
        if progress is not None:
            with lock:  # the outputs' threads report one at a time
                progress(replace(p, elapsed=time.perf_counter() - t0))

    orders, spaces = None, [base.term_space] * len(names)
    if base.orders == "auto":  # every output in its own proposal
        relay(Progress("checking data"))  # the segments, then each output's scan
        relay(Progress("orders"))
        base, orders, spaces = _choose_mimo_orders(record, base)
    base = _with_regressors(record, base)  # presets on the chosen lags

    def one(i: int):
        space = output_space(spaces[i], names, i)
        return run_single_job(_view(record, space, names, i),
                              replace(base, term_space=space), progress=relay,
                              progress_every=progress_every, metadata=metadata)

    outputs = in_threads(one, len(names), _outputs_at_once(record, base, spaces))
    seconds = {name: r.seconds.get("total", 0.0) for name, r in zip(names, outputs)}
    model = MimoModel.joined(names, tuple(record.input_names), [r.model for r in outputs])
    est, val, _ = validation_segments(record, base)
    # the coupled judgement, in both focuses: the joined model, its joint refinement
    # and the linear MIMO ARX structures compete on the coupled run
    chosen, account = _select_around(model, u, Y, est, lambda i, n: relay(
        Progress("refinement", i, n)))
    if chosen is not model:
        model = _take_coupled_choice(model, chosen, account, outputs, record, settings, val)
    model.metadata["coupled_selection"] = account
    if orders is not None:
        model.metadata["orders"] = orders
    cross = []
    if settings.validation != "none":
        cross = _validate_coupled(model, outputs, u, Y, val, settings)
    data = model.metadata["data"] = outputs[0].data
    model.metadata["ranges"] = data_ranges(u, Y, est, record.input_names, record.output_names)
    model.metadata.update(record.metadata())
    seconds["total"] = time.perf_counter() - t0
    model.metadata["identify_seconds"] = round(seconds["total"], 4)
    model.metadata.update(metadata or {})
    times = record.row_seconds(val, model.max_lag) if settings.validation != "none" else None
    return MimoJobResult(model, outputs, cross, data, seconds, times)


def _select_around(model: MimoModel, u: np.ndarray, Y: np.ndarray, est: list, progress
                   ) -> tuple[MimoModel, dict]:
    """The coupled judgement, on the deviations from the point the outputs' jobs used.

    The outputs' own jobs identified around the estimation data's means when the
    record sits far from zero (:mod:`~spm_sysid.core.model.operating_point`); the
    coupled runs, the joint refinement and the linear MIMO ARX finalists compare on
    the same deviations, and the choice is written in the record's units. The
    joined model itself is returned as it is when it is chosen.
    """
    offsets, reason = {}, ""
    for m in model.models:
        doc = m.metadata.get("operating_point") or {}
        offsets.update({**doc.get("inputs", {}), **doc.get("output", {})})
        reason = reason or doc.get("reason", "")
    if not any(offsets.values()):
        return select_coupled(model, u, Y, est, progress)

    def point(m) -> OperatingPoint:
        space = m.term_space
        return OperatingPoint(tuple(offsets.get(n, 0.0) for n in space.inputs),
                              offsets.get(space.output, 0.0), reason)

    u = np.asarray(u, dtype=float)
    du = u - np.array([offsets.get(n, 0.0) for n in model.inputs]).reshape(
        (1, -1) if u.ndim == 2 else ())
    dY = Y - np.array([offsets.get(n, 0.0) for n in model.outputs])
    around = replace(model, models=[in_deviations(m, point(m)) for m in model.models])
    chosen, account = select_coupled(around, du, dY, est, progress)
    if chosen is around:
        return model, account
    return replace(chosen, models=[in_record_units(m, point(m)) for m in chosen.models]
                   ), account


def _take_coupled_choice(model: MimoModel, chosen: MimoModel, account: dict, outputs: list,
                         record: Record, settings, val: list) -> MimoModel:
    """The coupled judgement's choice returned: each output's model, account and report.

    The selection account describes the model returned, not the output's own choice
    (kept as ``own_choice``).
    """
    u, Y = record.u, record.y
    model = replace(chosen, metadata={**model.metadata, **chosen.metadata})
    model.metadata["joint_criterion"] = MimoModel.joined(
        model.outputs, model.inputs, model.models).metadata["joint_criterion"]
    for i, r in enumerate(outputs):
        own = r.model.metadata.get("selection")
        r.model = model.models[i]
        r.model.metadata["selection"] = {
            "method": "coupled", "what": "coupled free-run",
            "folds": int(account.get("folds") or 0), "chosen": account.get("chosen"),
            "fitted": account.get("fitted"),
            "held_out_mse": account.get("held_out_error"),
            "note": "chosen with the other outputs by the coupled judgement",
            **({"own_choice": own} if own else {})}
        if r.report is not None:
            r.report = validate_model(
                r.model, augmented_inputs(u, Y, i), Y[:, i],
                correlation_lags=settings.correlation_lags,
                segment=settings.validation, segments=val,
                horizon=settings.horizon or None)
    return model


def _validate_coupled(model: MimoModel, outputs: list, u: np.ndarray, Y: np.ndarray,
                      val: list, settings) -> list:
    """Cross-correlation tests of the outputs' residuals; each report on the coupled run.

    An output whose own largest lag is below the coupled model's (``orders: auto``
    gives each output its own space) is validated again from the coupled run's
    first row of each segment, so that every report has the coupled run's rows.
    """
    for i, r in enumerate(outputs):
        if r.report is not None and r.model.term_space.max_lag < model.max_lag:
            r.report = validate_model(
                r.model, augmented_inputs(u, Y, i), Y[:, i],
                correlation_lags=settings.correlation_lags, segment=settings.validation,
                segments=coupled_rows(model, i, val), horizon=settings.horizon or None)
    cross = couple_reports(model, u, Y, val, [r.report for r in outputs],
                           settings.correlation_lags)
    for i, r in enumerate(outputs):
        if r.report is not None:
            r.model.metadata["validation"] = {**r.report.to_dict(), "free_run_coupled": True}
            set_explained_warning(r.model.metadata)
            store_monitor_reference(r.model.metadata, r.report.residuals,
                                    augmented_inputs(u, Y, i))
    model.metadata["cross_correlation_tests"] = [t.to_dict() for t in cross]
    return cross
