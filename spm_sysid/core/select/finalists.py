"""Validated selection for simulation: screen, judge finalists on held-out blocks, guard.

1. **Screen** every candidate, and the full linear ARX structure of every order
   in the space, by the criterion of its free-run error after a short
   refinement on the estimation data (:class:`~.simulation.SimulationScorer`;
   a long record's refinement windows).
2. **Finalists**: for each highest degree (linear, quadratic, ...) the best
   screened structures of each size, up to
   :data:`~spm_sysid.core.defaults.FINALISTS` sizes spread over the range (the
   group's best always among them), and every linear ARX structure.
3. **Judge** each finalist on the held-out blocks twice (:data:`ESTIMATORS`):
   each fold fits least squares on its rows, and that refined on its free-run
   error; the errors are gathered per sub-block
   (:func:`~spm_sysid.core.select.folds.sub_blocks`), each a separate held-out
   estimate; a run that leaves the measured range rejects the finalist.
4. **Choose** with the one linear/nonlinear call
   (:func:`~spm_sysid.core.select.call.linear_or_nonlinear`).
5. **Finish**: the choice is fitted on all data (least squares, or refined to
   convergence) and must pass the guard
   (:func:`~spm_sysid.core.select.guard.stress_check`), with its nonlinear
   terms shrunk if that is what it takes; otherwise the next by the call.

A long record (:func:`~spm_sysid.core.select.folds.is_long`) is judged on blocks
laid once and cut in sub-blocks, with one finalist per size and shorter fold
refinements (:data:`~spm_sysid.core.defaults.LONG_ROWS`): its cost stays about
that of a record of :data:`~spm_sysid.core.defaults.REFINE_ROWS` samples.

No model of the screening is changed: each step makes its own.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np

from ..defaults import (
    FINALISTS,
    FOLD_STEPS,
    LONG_POLISH_EVALUATIONS,
    LONG_POLISH_STEPS,
    PER_SIZE,
    POLISH_SPACE,
    SEARCH_STEPS,
    SIGNIFICANCE,
)
from ..errors import DataError
from ..fit.evaluator import key_mask, mask_key
from ..fit.refine import refine_simulation
from ..model.narx import NarxModel
from ..progress import Progress
from .call import Call, linear_or_nonlinear
from .folds import (
    final_samples,
    final_steps,
    is_long,
    refinement_windows,
    sub_blocks,
    windowed_rows,
)
from .guard import shrink_to_hold, stress_check
from .scores import Scores, mean_and_stderr
from .simulation import (
    SimulationScorer,
    free_run_covariance,
    linear_orders,
    linear_structures,
    simulation_value,
)

__all__ = ["ESTIMATORS", "FoldRun", "validated_simulation"]

#: How a finalist's coefficients are estimated on a fold; each is judged on the held-out
#: blocks and competes: least squares, or least squares refined on the free-run error
#: (which helps nonlinear structures most and on short records can overfit).
ESTIMATORS = ("least squares", "refined")


@dataclass(frozen=True)
class FoldRun:
    """A structure's held-out free run on one fold.

    ``at`` and ``squared``: the held-out samples and the squared errors there;
    ``diverged_at``: the sample where the run left the measured range; neither:
    the structure cannot be fitted on the fold's rows.
    """

    at: np.ndarray | None = None
    squared: np.ndarray | None = None
    diverged_at: int | None = None

    @property
    def fitted(self) -> bool:
        return self.at is not None or self.diverged_at is not None


def fold_runs(problem, fold, mask: np.ndarray, steps: int = FOLD_STEPS,
              dead: tuple[FoldRun | None, FoldRun | None] = (None, None),
              fallback: np.ndarray | None = None) -> tuple[FoldRun, FoldRun]:
    """The held-out runs of the structure fitted on the fold, one per estimator.

    Least squares on the fold's rows, then refined from there on the free-run
    error of the fold's segments (at most ``steps`` evaluations, on a long
    record's :func:`~spm_sysid.core.select.folds.refinement_windows`); a
    refinement that fails judges the least-squares fit twice, unless a
    ``fallback`` start is given (the polished structure's screened coefficients,
    :meth:`ValidatedSimulation._fallback`): the refinement then runs again from there.

    ``dead``: an estimator's run that already left the range on an earlier fold
    (None: none did). Its held-out error is infinite whatever this fold gives, so
    that run is returned again instead of being computed (the refinement, the
    costly part, is skipped); whether the fold's rows fit the structure is
    still checked, as an unfit fold decides the structure's errors first.
    """
    u, y = problem.u, problem.y
    try:
        fit = problem.fit(mask, rows=fold.train)
    except ValueError:
        return FoldRun(), FoldRun()
    if dead[0] is not None and dead[1] is not None:
        return dead
    model = problem.model(mask, fit)
    lag = problem.term_space.max_lag
    at = np.concatenate([np.arange(a + lag, b) for a, b in fold.held_out])

    def held_out(m: NarxModel) -> FoldRun:
        yhat, diverged = m.run(u, y, None, fold.held_out)
        if diverged is not None:
            return FoldRun(diverged_at=int(diverged))
        e = m.measured(y, fold.held_out) - yhat
        return FoldRun(at, e * e)

    least_squares = dead[0] or held_out(model)
    if dead[1] is not None:
        return least_squares, dead[1]
    windows = refinement_windows(fold.train_segments, lag)
    ref = refine_simulation(model, u, y, windows, max_evaluations=steps)
    if not (ref.success and np.isfinite(ref.sse)) and fallback is not None:
        ref = refine_simulation(model.with_coefficients(fallback), u, y, windows,
                                max_evaluations=steps)
    if not (ref.success and np.isfinite(ref.sse)):
        least_squares = held_out(model) if dead[0] is not None else least_squares
        return least_squares, least_squares
    return least_squares, held_out(model.with_coefficients(ref.coefficients))


def sub_block_errors(runs: list[FoldRun], label: np.ndarray, n_sub: int) -> list[float]:
    """Each sub-block's held-out MSE over the folds' runs (inf: a run diverged; NaN: unfit)."""
    if not all(r.fitted for r in runs):
        return [np.nan] * n_sub
    if any(r.diverged_at is not None for r in runs):
        return [np.inf] * n_sub
    sse, count = np.zeros(n_sub), np.zeros(n_sub)
    for r in runs:
        ids = label[r.at]
        np.add.at(sse, ids, r.squared)
        np.add.at(count, ids, 1)
    return list(np.where(count > 0, sse / np.maximum(count, 1), np.nan))


def finalists(screened: dict, term_space, per_size: int = PER_SIZE
              ) -> list[tuple[float, bytes]]:
    """The best screened structures of each size (``per_size``), sizes spread, by degree.

    Structures are grouped by their highest degree (linear, quadratic, ...):
    in-sample, a nonlinear structure nearly always beats a linear one of the
    same size, yet off the estimation data the linear one often simulates
    better, so each group sends its own finalists to the held-out blocks. In
    each group at most :data:`FINALISTS` sizes, spread on a log scale (small
    models are cheap to overlook and often what the data support), the group's
    best among them.
    """
    n_terms = term_space.n_terms
    degree = term_space.term_degrees
    groups: dict[int, dict[int, list[tuple[float, bytes]]]] = {}
    for key, (value, _) in screened.items():
        if np.isfinite(value):
            mask = key_mask(key, n_terms)
            by_size = groups.setdefault(int(degree[mask].max()), {})
            by_size.setdefault(int(mask.sum()), []).append((value, key))
    out = []
    for by_size in groups.values():
        sizes = sorted(by_size)
        if len(sizes) > FINALISTS:
            best_size = min(sizes, key=lambda k: min(by_size[k])[0])
            targets = np.geomspace(sizes[0], sizes[-1], FINALISTS - 1)
            spread = {min(sizes, key=lambda k: abs(np.log(k) - np.log(t))) for t in targets}
            sizes = sorted(spread | {best_size})
        out += [item for k in sizes for item in sorted(by_size[k])[:per_size]]
    return sorted(out)


@dataclass
class Judged:
    """The finalists' held-out errors: one entry per finalist and estimator."""

    scores: Scores
    blocks: list[list[float]]
    estimator: list[str]


class ValidatedSimulation:
    """Validated selection for simulation on one problem (see the module doc).

    Parameters
    ----------
    problem, folds, criterion, max_terms, report, started
        The problem, its held-out folds, the criterion, the size limit (0: none),
        the progress callback and the job's start time.
    integrating : bool
        The output integrates (the open-loop check): the guard drives it with its
        own input only (:func:`~spm_sysid.core.select.guard.stress_check`).
    """

    def __init__(self, problem, folds, criterion, max_terms, report, started,
                 integrating: bool = False) -> None:
        self.problem, self.folds, self.crit = problem, folds, criterion
        self.integrating = integrating  # the guard checks its own input only
        self.report, self.started = report, started
        self.scorer = SimulationScorer(
            problem, criterion, steps=SEARCH_STEPS, max_terms=max_terms, progress=report,
            started=started,
            segments=refinement_windows(problem.segments, problem.term_space.max_lag),
            phase="screening")
        self.degree = problem.term_space.term_degrees
        self.polished: bytes | None = None  # the polish's end (a long record's)

    def screen(self, candidates) -> list[tuple[float, bytes]]:
        """Step 1 and 2: every candidate and linear structure scored; the finalists."""
        linear = linear_structures(self.problem)
        self.scorer.total = len(candidates) + len(linear)
        for mask in list(candidates) + list(linear):
            self.scorer(mask)
        screened = dict(self.scorer.scored)
        finals = finalists(screened, self.problem.term_space,
                           1 if is_long(self.problem) else PER_SIZE)
        self.polished = polished = self.polish() if is_long(self.problem) else None
        if polished is not None and polished not in {key for _, key in finals}:
            finals.append((self.scorer.scored[polished][0], polished))
        keys = {key for _, key in finals}
        finals += [(screened[mask_key(m)][0], mask_key(m)) for m in linear
                   if mask_key(m) not in keys and np.isfinite(screened[mask_key(m)][0])]
        if not finals:
            raise DataError("every candidate structure's free-run simulation diverges on "
                            "the estimation data (or cannot be fitted): no model simulates"
                            + still_inputs(self.problem))
        return finals

    def polish(self) -> bytes | None:
        """Step 1b, on a long record: moves from the best screened nonlinear structure.

        The candidates come from the one-step search; what simulates best is often a
        few terms away. :data:`~spm_sysid.core.defaults.LONG_POLISH_STEPS` moves
        (one term of the space added or removed, warm-started, scored in-sample as
        the screening scores) from the best nonlinear structure; where they end
        joins the finalists (its key; None: not polished), and the held-out blocks
        decide. Only on a long record (thousands of rows per term make the
        in-sample score a fair guide; on a short one it would find the noise) and
        in spaces of at most :data:`~spm_sysid.core.defaults.POLISH_SPACE` terms
        (each move tries every term: beyond that it costs more than the rest).
        """
        n = self.problem.term_space.n_terms
        nonlinear = [(value, key) for key, (value, _) in self.scorer.scored.items()
                     if np.isfinite(value) and self.degree[key_mask(key, n)].max() > 1]
        if not nonlinear or n > POLISH_SPACE:
            return None
        self.scorer.total += LONG_POLISH_STEPS * int(self.problem.usable.sum())  # at most
        found = self.scorer.descend(key_mask(min(nonlinear)[1], n), self.problem.usable,
                                    LONG_POLISH_STEPS, LONG_POLISH_EVALUATIONS)
        return mask_key(found.mask)

    def judge(self, finals: list[tuple[float, bytes]]) -> Judged:
        """Step 3: each finalist and estimator on the held-out sub-blocks."""
        n = self.problem.term_space.n_terms
        label = sub_blocks(self.problem, self.folds)
        n_sub = int(label.max()) + 1
        steps = SEARCH_STEPS if is_long(self.problem) else FOLD_STEPS
        out = Judged(Scores(), [], [])
        self.report(Progress("held-out blocks", 0, len(finals),
                             elapsed=time.perf_counter() - self.started))
        for done, (_, key) in enumerate(finals):
            mask = key_mask(key, n)
            both = self._fold_runs(mask, steps, self._fallback(key))
            rejected = False
            for j, how in enumerate(ESTIMATORS):
                values = sub_block_errors([b[j] for b in both], label, n_sub)
                mean, stderr = mean_and_stderr(values)
                out.scores.masks.append(mask)
                out.scores.mean.append(mean)
                out.scores.stderr.append(stderr)
                out.blocks.append(values)
                out.estimator.append(how)
                rejected |= not np.isfinite(mean)
            out.scores.rejected += rejected
            self.report(Progress("held-out blocks", done + 1, len(finals),
                                 elapsed=time.perf_counter() - self.started))
        return out

    def _fallback(self, key: bytes) -> np.ndarray | None:
        """The polished structure's start for a fold refinement whose least squares fail.

        Its screened coefficients (None for any other finalist). The polish refines
        each move from its neighbour's coefficients, never from least squares, so its
        end may be a structure whose least-squares fit leaves the range though its
        refined fit simulates well; on a long record (the only one polished) a
        fold's optimum is the record's, and this start spares it a rejection its
        refined fit does not deserve. Every other finalist starts from least squares
        only, as it was screened.
        """
        model = self.scorer.scored[key][1]
        return model.coefficients if key == self.polished and model is not None else None

    def _fold_runs(self, mask: np.ndarray, steps: int, fallback: np.ndarray | None = None
                   ) -> list[tuple[FoldRun, FoldRun]]:
        """Each fold's pair of runs; an estimator that left the range is not run again."""
        out, dead = [], [None, None]
        for fold in self.folds:
            pair = fold_runs(self.problem, fold, mask, steps, (dead[0], dead[1]), fallback)
            dead = [d or (r if r.diverged_at is not None else None) for d, r in zip(dead, pair)]
            out.append(pair)
        return out

    def choose(self, judged: Judged) -> tuple[Call, dict]:
        """Step 4: the linear/nonlinear call, and its account for the document."""
        s = judged.scores
        call = linear_or_nonlinear(
            s.mean, s.stderr, [int(m.sum()) for m in s.masks],
            [int(self.degree[m].max()) <= 1 for m in s.masks], judged.blocks)
        if call.linear is None:
            account = {"choice": "nonlinear", "reason": "no linear finalist simulated every "
                       "held-out block"}
        else:
            lin = call.linear
            account = {"best_linear_terms": int(s.masks[lin].sum()),
                       "best_linear_held_out_mse": s.mean[lin],
                       "best_linear_held_out_stderr": s.stderr[lin],
                       "blocks": len(judged.blocks[lin]), "significance": SIGNIFICANCE}
            if call.challenger is not None:
                account.update(nonlinear_terms=int(s.masks[call.challenger].sum()),
                               ratio=call.ratio, p_value=call.p_value)
            account["choice"] = call.choice
        account["estimator"] = judged.estimator[call.order[0]] if call.order else None
        account.update(self.linear_arx(judged))
        return call, account

    def linear_arx(self, judged: Judged) -> dict:
        """The yardstick in the account: the full linear ARX fitted by least squares.

        Of the orders judged (every one is a finalist), the one with the lowest mean
        held-out error: its order, mean and standard error (empty when none simulated
        every block). A user compares the returned model's held-out error with this,
        the one-line ARX fit, on the same blocks.
        """
        s = judged.scores
        orders = {mask_key(m): k for k, m in linear_orders(self.problem.term_space,
                                                             self.problem.usable)}
        rows = [(s.mean[i], orders[mask_key(m)], s.stderr[i])
                for i, m in enumerate(s.masks)
                if judged.estimator[i] == "least squares" and mask_key(m) in orders
                and np.isfinite(s.mean[i])]
        if not rows:
            return {}
        mean, order, stderr = min(rows)
        return {"linear_arx_order": order, "linear_arx_held_out_mse": mean,
                "linear_arx_held_out_stderr": stderr}

    def linear_sse(self, judged: Judged) -> float:
        """In-sample free-run SSE of the best screened linear finalist (inf: none)."""
        best = np.inf
        u, y, segments = self.problem.u, self.problem.y, self.problem.segments
        for mask, mean in zip(judged.scores.masks, judged.scores.mean):
            model = self.scorer.scored[mask_key(mask)][1]
            if np.isfinite(mean) and self.degree[mask].max() <= 1 and model is not None:
                yhat, at = model.run(u, y, None, segments)
                if at is None:
                    e = model.measured(y, segments) - yhat
                    best = min(best, float(e @ e))
        return best

    def fit_all(self, mask: np.ndarray, estimator: str):
        """Step 5: the finalist fitted on all data as it was judged; (model, refinement, why).

        ``why`` is the guard's reason when the model does not hold (None: it does).
        """
        problem = self.problem
        u, y, segments = problem.u, problem.y, problem.segments
        screened = self.scorer.scored[mask_key(mask)][1]
        if estimator == "least squares":  # as the held-out blocks judged it
            model = screened.with_coefficients(problem.model(mask).coefficients)
            return model, None, stress_check(model, u, y, segments, self.integrating)
        self.report(Progress("refinement", elapsed=time.perf_counter() - self.started))
        samples = final_samples(segments, problem.term_space.max_lag,
                                8 * len(screened.term_indices), single=True)
        final = refine_simulation(screened, u, y, samples, **final_steps(problem))
        # fitted on windows: the start's SSE on every row, as the account compares them
        if windowed_rows(samples, segments, problem.term_space.max_lag) is not None:
            start = screened.measured(y, segments) - screened.run(u, y, None, segments)[0]
            final = replace(final, sse_start=float(start @ start))
        model = screened.with_coefficients(screened.coefficients)
        if final.success and np.isfinite(final.sse):
            model = screened.with_coefficients(final.coefficients)
        why = stress_check(model, u, y, segments, self.integrating)
        if why and final.success:  # the refinement may be what left the range
            model = screened.with_coefficients(screened.coefficients)
            why = stress_check(model, u, y, segments, self.integrating)
        return model, final, why

    def finish(self, model: NarxModel, mask, estimator, final, shrunk) -> NarxModel:
        """The returned model's criterion, errors, uncertainty and account."""
        problem, crit = self.problem, self.crit
        u, y, segments = problem.u, problem.y, problem.segments
        e = model.measured(y, segments) - model.run(u, y, None, segments)[0]
        sse = float(e @ e)
        one_step = model.residuals(u, y, segments)
        model = replace(model, criterion=crit.name, n_samples=problem.n_samples,
                        mse=float(one_step @ one_step) / len(one_step),
                        criterion_value=simulation_value(crit, sse, problem.rows, mask,
                                                         model.coefficients, problem))
        model.uncertainty, covariance = free_run_covariance(model, problem)
        model.metadata = {"simulation": {
            "estimator": estimator, **covariance,
            "refinement": final.message if final is not None else "none: least squares "
                          "simulated the held-out blocks better",
            "free_run_sse": sse,
            **({"least_squares_free_run_sse": final.sse_start} if final is not None else {}),
            **({"shrunk_nonlinear_terms": shrunk} if shrunk is not None else {}),
            "criterion_meaning": f"{crit.name.upper()} of the free-run simulation error "
                                 "(SSE of the simulated output) on the estimation data"}}
        return model


def validated_simulation(problem, candidates, folds, crit, max_terms, report,
                         started, integrating: bool = False) -> tuple[NarxModel, dict]:
    """Simulation focus, validated (see the module doc): the model and its account."""
    job = ValidatedSimulation(problem, folds, crit, max_terms, report, started, integrating)
    finals = job.screen(candidates)
    judged = job.judge(finals)
    call, decision = job.choose(judged)
    s, linear_sse = judged.scores, job.linear_sse(judged)
    held = first_that_holds(job, call, judged, linear_sse)
    removed, reasons, i = held.removed, held.reasons, held.index
    if i is not None:
        mask, how = s.masks[i], judged.estimator[i]
        if i != call.order[0]:
            decision = {**decision, "fallback": "the chosen structure failed the guard; "
                        f"the next by the rule has {int(mask.sum())} terms"}
        decision = returned_account(decision, call, i, int(mask.sum()),
                                    bool(job.degree[mask].max() > 1), held.shrunk, reasons)
        return job.finish(held.model, mask, how, held.final, held.shrunk), {
            "held_out_mse": s.mean[i], "held_out_stderr": s.stderr[i],
            "candidates": len(candidates), "screened": len(job.scorer.scored),
            "finalists": len(finals), "removed_by_guard": removed,
            "left_range_held_out": s.rejected,
            "linear_or_nonlinear": decision, **({"guard_reasons": reasons} if reasons else {})}
    raise DataError(f"no finalist structure simulates within the output's range: "
                    f"{s.rejected} of {len(finals)} left it on the held-out blocks, "
                    f"{removed} were removed by the stability guard"
                    + (f" ({reasons[0]})" if reasons else "")
                    + "; the record may need other terms (a larger space, --orders auto) or "
                    "the prediction focus")


def still_inputs(problem) -> str:
    """Why nothing simulates when every input is constant ('' when one moves)."""
    u = problem.u[problem.row_times]
    if not u.size or np.any(u != u[:1]):
        return ""
    names = problem.term_space.inputs
    levels = ", ".join(f"{v:g}" for v in u[0])
    return (f"; the input{'s' if len(names) > 1 else ''} {', '.join(names)} "
            f"{'are' if len(names) > 1 else 'is'} constant ({levels} throughout): nothing "
            "excites the system, so a free run can only drift from its start; record while "
            "the input moves (steps, a chirp, random steps), or use the prediction focus for "
            "a model of the output alone")


def returned_account(decision: dict, call: Call, returned: int, terms: int, nonlinear: bool,
                     shrunk: float | None, reasons: list[str]) -> dict:
    """The call's account rewritten for the model returned (after guard, shrinkage, fallback).

    ``choice`` and ``terms`` describe the returned model; ``tested`` is what the
    paired test decided; ``challenger_fate`` says in one clause what became of the
    tested nonlinear finalist: returned (shrunk, if it was), removed by the
    stability guard (its reason), or not better than the best linear one.
    """
    out = {**decision, "tested": decision.get("choice"),
           "choice": "nonlinear" if nonlinear else "linear", "terms": terms}
    if shrunk is not None:
        out["shrunk_nonlinear_terms"] = shrunk
    if call.challenger is None:
        return out
    if returned == call.challenger:
        fate = "returned"
        if shrunk is not None:
            fate += f", its nonlinear coefficients scaled by {shrunk:g} to pass the stability guard"
    elif call.choice == "nonlinear":
        fate = "removed by the stability guard" + (f" ({reasons[0]})" if reasons else "")
    else:
        fate = "not better than the best linear one by more than the noise"
    out["challenger_fate"] = fate
    return out


@dataclass
class Held:
    """The finalist returned after the guard (index None: none held) and what was removed."""

    index: int | None
    model: NarxModel | None = None
    final: object = None
    shrunk: float | None = None
    removed: int = 0
    reasons: list[str] = field(default_factory=list)


def first_that_holds(job: ValidatedSimulation, call: Call, judged: Judged,
                     linear_sse: float) -> Held:
    """The first finalist, in the call's order, whose model fitted on all data holds.

    Each is fitted as it was judged (:meth:`ValidatedSimulation.fit_all`) and
    must pass the stability guard. The first nonlinear one the guard removes is
    shrunk (:func:`~spm_sysid.core.select.guard.shrink_to_hold`) only when no
    other nonlinear finalist of the order holds, before the first linear one:
    a smaller nonlinear effect is a last resort, not a first.
    """
    s = judged.scores
    u, y, segments = job.problem.u, job.problem.y, job.problem.segments
    removed, reasons, tried, pending = 0, [], set(), None
    for i in [*call.order, None]:
        nonlinear = i is not None and bool(job.degree[s.masks[i]].max() > 1)
        if pending is not None and not nonlinear:  # no other nonlinear finalist held
            j, model, final = pending
            pending, kept = None, shrink_to_hold(model, u, y, segments, linear_sse,
                                                 job.integrating)
            if kept is not None:
                return Held(j, model.with_coefficients(kept[1]), final, kept[0],
                            removed - 1, reasons)
        if i is None:
            break
        key = (mask_key(s.masks[i]), judged.estimator[i])
        if key in tried:
            continue
        tried.add(key)
        model, final, why = job.fit_all(s.masks[i], judged.estimator[i])
        if why is None:
            return Held(i, model, final, None, removed, reasons)
        removed += 1
        reasons.append(why)
        if nonlinear and pending is None:
            pending = (i, model, final)
    return Held(None, removed=removed, reasons=reasons)
