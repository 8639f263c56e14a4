"""The paper's study: SPM versus the plain GA over repeated seeded runs.

For every combination of criterion, population size and SPM fraction, ``runs``
GA runs are made with seeds ``seed, seed + 1, ...`` -- the *same* seeds for
every setting (common random numbers), so settings differ only by their
parameters. Runs go to a process pool, one process per core, or to a Dask
cluster; each process builds the regression problem
(:class:`~spm_sysid.core.fit.problem.Problem`) once, and each run is
:func:`~spm_sysid.core.identify.identify_problem` with the run's settings:
the very computation ``identify`` does with those settings and that seed.

Per setting the summary counts the runs that *reached the best*: whose final
structure equals the best structure found across all runs of that criterion
(all population sizes and fractions), as the paper does ("the same, presumably
most optimal model"). Fisher's exact test (scipy, two-sided) compares each
fraction's reach count with that of s = 0 at the same criterion and population.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict
from pathlib import Path

import numpy as np

from ..core.errors import SettingsError
from ..core.fit.problem import Problem
from ..core.identify import identify_problem
from ..core.jobs import JobSettings
from ..core.model.terms import TermSpace
from ..core.search.ga import GAConfig
from ..core.settings import JOB_GROUPS, SETTINGS, check
from ..core.validate.validation import metrics
from .study_results import (
    RunRecord,
    SettingSummary,
    StudyRecords,
    mark_reached,
    summarise,
    summary_table,
    write_results,
)

__all__ = ["ExperimentConfig", "RunRecord", "SettingSummary", "StudyRecords", "mark_reached",
           "run_experiment", "summarise", "summary_table", "write_results"]

#: The study's own settings (the grid and how it runs); every other key is a job setting.
STUDY_FIELDS = ("criteria", "populations", "spm_fractions", "runs", "seed", "workers",
                "certify_reference")

#: Grid lists and the job setting each lists values of.
GRID = {"criteria": "criterion", "populations": "population_size",
        "spm_fractions": "spm_fraction"}


def _check_grid_list(name: str, setting: str, values) -> None:
    """A grid list: non-empty, each value valid for its setting, none twice."""
    if not isinstance(values, list) or not values:
        raise SettingsError(f"{name} must be a non-empty list")
    checked = [check(setting, v) for v in values]  # 20.9 is not a population
    if len(set(checked)) != len(checked):
        raise SettingsError(f"{name} lists a value more than once: {values} (each "
                            "setting of the grid is run once)")


class ExperimentConfig:
    """What to run; defaults are the paper's study (180 runs).

    Parameters
    ----------
    criteria, populations, spm_fractions : list
        The grid: values of the settings ``criterion``, ``population_size`` and
        ``spm_fraction`` (checked by the schema; no value twice).
    runs : int
        Runs per setting, with seeds ``seed .. seed + runs - 1``.
    seed : int
        The first seed.
    workers : int
        Local processes (0: one per core).
    certify_reference : bool
        Prove each AIC/BIC optimum by branch and bound after the runs (within
        ``certify_time_limit``); "reached" then counts runs that found it.
    **settings
        Any job setting of the schema (:mod:`spm_sysid.core.settings`) by its one
        name: ``generations``, ``fitness``, ``ny``, ``focus``, ``certify_time_limit``
        ... (a nested ``term_space`` mapping of ``ny``, ``nu``, ``degree``,
        ``delay``, ``constant`` is read too). Checked once, here; the study's
        defaults are the schema's.

    Raises
    ------
    SettingsError
        An unknown setting, a value out of range, a grid value given twice.
    """

    def __init__(self, *, criteria=None, populations=None, spm_fractions=None, runs: int = 15,
                 seed: int = 0, workers: int = 0, certify_reference: bool = True,
                 term_space: dict | None = None, **settings) -> None:
        self.criteria = ["aic", "bic", "pmic2"] if criteria is None else criteria
        self.populations = [200, 100] if populations is None else populations
        self.spm_fractions = [0.0, 0.15] if spm_fractions is None else spm_fractions
        self.runs, self.seed, self.workers = runs, seed, workers
        self.certify_reference = certify_reference
        if term_space is not None:
            allowed = {"ny", "nu", "degree", "delay", "constant", "inputs", "output"}
            if not isinstance(term_space, dict):
                raise SettingsError("term_space must be a mapping of ny, nu, degree, delay, "
                                    "constant")
            unknown = set(term_space) - allowed
            if unknown:
                raise SettingsError(f"term_space: unknown setting(s) {sorted(unknown)}")
            settings = {**term_space, **settings}
        for name in ("certify", "auto_certify_time_limit"):
            if settings.get(name, 0) not in (0, False):
                raise SettingsError(
                    f"{name}: in a study, the reference optimum is certified with "
                    "certify_reference (true by default); certifying every run would replace "
                    "what the study measures")
        # a study measures the GA: no polish (unless asked), no certification of each run
        settings = {"polish": False, **settings, "auto_certify_time_limit": 0.0}
        job_names = {n for n, st in SETTINGS.items() if st.group in JOB_GROUPS}
        unknown = set(settings) - job_names - {"inputs", "output"}
        if unknown:
            raise SettingsError(f"unknown setting(s) {sorted(unknown)}")
        self.settings = dict(settings)
        self._check()

    def _check(self) -> None:
        if not isinstance(self.runs, int) or isinstance(self.runs, bool) or self.runs < 1:
            raise SettingsError(f"runs must be an integer >= 1, got {self.runs!r}")
        if not isinstance(self.workers, int) or self.workers < 0:
            raise SettingsError(f"workers must be an integer >= 0, got {self.workers!r}")
        if check("seed", self.seed) < 0:
            raise SettingsError(f"seed (the study's first seed) must be >= 0, got {self.seed}")
        if not isinstance(self.certify_reference, bool):
            raise SettingsError(f"certify_reference must be true or false, got "
                                f"{self.certify_reference!r}")
        for name, setting in GRID.items():
            _check_grid_list(name, setting, getattr(self, name))
        # every cell's settings, checked once by the schema (unknown criteria included)
        for c in self.criteria:
            for pop in self.populations:
                for s in self.spm_fractions:
                    self.job(c, pop, s)

    def __getattr__(self, name: str):
        """A job setting by its name (``config.generations``): given, or the default."""
        if name.startswith("_") or name == "settings":
            raise AttributeError(name)
        if name in SETTINGS:
            return self.settings.get(name, SETTINGS[name].default)
        raise AttributeError(f"ExperimentConfig has no setting {name!r}")

    def job(self, criterion: str, population: int, spm: float) -> JobSettings:
        """The settings of one cell of the grid (what ``identify`` would run)."""
        return JobSettings.from_values({**self.settings, "criterion": criterion,
                                        "population_size": int(population),
                                        "spm_fraction": float(spm)})

    def ga(self, population: int, spm: float) -> GAConfig:
        """The GA settings of one cell."""
        return self.job(self.criteria[0], population, spm).ga

    @property
    def term_space(self) -> TermSpace:
        """The candidate terms of every run."""
        return self.job(self.criteria[0], self.populations[0], self.spm_fractions[0]).term_space

    def to_dict(self) -> dict:
        """The study's settings as plain data (documents, the resume check)."""
        return {**{k: getattr(self, k) for k in STUDY_FIELDS}, "settings": dict(self.settings)}

    @classmethod
    def from_yaml(cls, path: str | Path, **overrides) -> ExperimentConfig:
        """Read settings from a YAML mapping; ``overrides`` (not None) win."""
        import yaml

        try:
            data = yaml.safe_load(Path(path).read_text())
        except yaml.YAMLError as exc:
            raise SettingsError(f"{path} is not valid YAML: "
                                f"{' '.join(str(exc).split())}") from None
        return cls.from_mapping(data, str(path), **overrides)

    @classmethod
    def from_mapping(cls, data, source: str = "the settings", **overrides) -> ExperimentConfig:
        """Settings from a mapping (e.g. read from YAML); ``overrides`` (not None) win."""
        data = {} if data is None else data
        if not isinstance(data, dict) or not all(isinstance(k, str) for k in data):
            raise SettingsError(f"{source}: expected a mapping of settings (name: value)")
        data = {**data, **{k: v for k, v in overrides.items() if v is not None}}
        try:
            return cls(**data)
        except SettingsError as exc:
            raise SettingsError(f"{source}: {exc}") from None


# -- workers --------------------------------------------------------------------------

_WORKER: dict = {}


def _one_run(task: tuple) -> RunRecord:
    """One run: ``identify_problem`` on the process's problem, with the cell's settings."""
    criterion, population, spm, run, seed = task
    problem, config = _WORKER["problem"], _WORKER["config"]
    job = config.job(criterion, population, spm)
    t0 = time.perf_counter()
    # the cell's settings, every one of them (a setting added to the schema reaches here)
    ident = identify_problem(problem, job.search.with_seed(seed), ga=job.ga, check_data=False)
    model = ident.model
    seconds = time.perf_counter() - t0
    free = metrics(model.measured(problem.y, problem.segments),
                   model.run(problem.u, problem.y, None, problem.segments)[0])["fit_percent"]
    return RunRecord(
        criterion=criterion, population_size=population, spm_fraction=spm, run=run, seed=seed,
        final_value=float(model.criterion_value), terms=model.terms,
        n_terms=len(model.terms), first_best_generation=ident.ga.first_best_generation,
        seconds=seconds, evaluations=ident.ga.evaluations,
        best_curve=ident.ga.history_array("best").tolist(), focus=job.focus,
        free_run_fit=None if not np.isfinite(free) else float(free),
    )


def _task(task: tuple, shared: tuple) -> RunRecord:
    """One run where the data come with the task (local pool or Dask worker)."""
    token, u, y, config = shared
    if _WORKER.get("token") != token:  # build the regression problem once per process
        _WORKER.update(token=token, config=config,
                       problem=Problem.from_signals(u, y, config.term_space))
    return _one_run(task)


def run_key(task: tuple) -> str:
    """The stable name of a run: criterion, population, fraction, run index."""
    return f"{task[0]}-{task[1]}-{task[2]:g}-{task[3]}"


def data_token(u: np.ndarray, y: np.ndarray, config: ExperimentConfig) -> str:
    """A fingerprint of the data and the study settings (resume checks it)."""
    import hashlib

    h = hashlib.sha256()
    for a in (np.ascontiguousarray(u, dtype=float), np.ascontiguousarray(y, dtype=float)):
        h.update(a.tobytes())
    cfg = {k: v for k, v in config.to_dict().items() if k not in ("workers",)}
    h.update(json.dumps(cfg, sort_keys=True).encode())
    return h.hexdigest()[:16]


def run_experiment(
    u: np.ndarray, y: np.ndarray, config: ExperimentConfig,
    progress: Callable[[int, int], None] | None = None, *,
    scheduler: str | None = None, out: str | Path | None = None, resume: bool = False,
) -> StudyRecords:
    """Run every (criterion, population, fraction, run) of the study.

    On this machine (``config.workers`` processes) or, with ``scheduler``, on a
    Dask cluster (:func:`spm_sysid.tools.runner.run_tasks`). Records come back in
    a fixed order (criterion, population, fraction, run), whatever runs them and in
    whatever order they finish, so the same seeds give the same list. With
    ``out``, each finished run is appended to ``out/runs.partial.jsonl`` at once;
    ``resume`` reads that file (it must belong to the same data and settings) and
    runs only what is missing. Runs that fail (after retries) are in
    ``records.failures`` with their errors, never silently left out.
    """
    from .runner import run_tasks

    tasks = _study_tasks(config)
    token = data_token(u, y, config)
    finished: dict[str, RunRecord] = {}
    partial = None
    if out is not None:
        partial, finished = _open_partial(Path(out), resume, token, tasks, config)
    todo = {k: t for k, t in tasks.items() if k not in finished}
    count = [len(finished)]
    if progress and finished:
        progress(len(finished), len(tasks))

    def on_done(outcome) -> None:
        if outcome.ok and partial is not None:
            with open(partial, "a") as f:
                f.write(json.dumps({"key": outcome.key, "record": asdict(outcome.result)})
                        + "\n")
                f.flush()
        count[0] += 1
        if progress:
            progress(count[0], len(tasks))

    outcomes = run_tasks(_task, todo, shared=(token, u, y, config),
                         scheduler=scheduler, workers=config.workers, on_done=on_done)
    records = _in_task_order(tasks, finished, outcomes)
    optima = (certify_optima(u, y, config, records) if config.certify_reference and records
              else {})
    mark_reached(records, optima)
    return records


def _study_tasks(config: ExperimentConfig) -> dict[str, tuple]:
    """Every (criterion, population, fraction, run, seed) of the grid, by its run key."""
    tasks = {}
    for c in config.criteria:
        for pop in config.populations:
            for s in config.spm_fractions:
                for r in range(config.runs):
                    t = (c, int(pop), float(s), r, config.seed + r)
                    tasks[run_key(t)] = t
    return tasks


def _open_partial(out: Path, resume: bool, token: str, tasks: dict,
                  config: ExperimentConfig) -> tuple[Path, dict[str, RunRecord]]:
    """OUT's file of finished runs, and the runs it holds when resuming (else none).

    An earlier study's runs are never overwritten without ``--force`` (the caller
    removes them) or ``--resume``.
    """
    out.mkdir(parents=True, exist_ok=True)
    partial, stamp = out / "runs.partial.jsonl", out / "study.json"
    finished: dict[str, RunRecord] = {}
    if resume:
        finished = _read_partial(partial, stamp, token, tasks)
    elif partial.exists():
        raise FileExistsError(
            f"{out} holds runs of an earlier study ({partial.name}); resume it with "
            "--resume, start over with --force, or choose another --out (nothing was "
            "overwritten)")
    stamp.write_text(json.dumps({"token": token, "config": config.to_dict()}, indent=1))
    return partial, finished


def _in_task_order(tasks: dict, finished: dict, outcomes: dict) -> StudyRecords:
    """The records in the grid's order (resumed or run here), with the failed runs."""
    records = StudyRecords()
    records.failures = [o for o in outcomes.values() if not o.ok]
    records.resumed = len(finished)
    for key in tasks:
        if key in finished:
            records.append(finished[key])
        elif key in outcomes and outcomes[key].ok:
            records.append(outcomes[key].result)
    return records


def _read_partial(partial: Path, stamp: Path, token: str, tasks: dict) -> dict:
    """Finished runs of an interrupted study (checked to be the same study)."""
    if not partial.exists():
        return {}
    if not stamp.exists() or json.loads(stamp.read_text()).get("token") != token:
        raise ValueError(f"{partial} belongs to another study (other data or settings); "
                         "it cannot be resumed with these")
    finished = {}
    for line in partial.read_text().splitlines():
        try:
            item = json.loads(line)
        except json.JSONDecodeError:  # a line cut short when the study was stopped
            continue
        if item.get("key") in tasks:
            finished[item["key"]] = RunRecord(**item["record"])
    return finished


def certify_optima(u: np.ndarray, y: np.ndarray, config: ExperimentConfig,
                   records: Sequence[RunRecord]) -> dict[str, dict]:
    """Certify each certifiable criterion's optimum, warm-started with the runs' best.

    Returns criterion -> certificate document (``status`` ``optimal`` or ``limit``).
    Only for the prediction focus (with the simulation focus the runs' values are
    criteria of the simulation error, which branch and bound does not search).
    """
    from ..core.search.certify import CERTIFIABLE
    from ..core.search.split import certify_data

    if config.focus != "prediction":
        return {}
    space = config.term_space
    names = space.term_names()
    out = {}
    for crit in dict.fromkeys(r.criterion for r in records):
        if crit not in CERTIFIABLE:
            continue
        best = min((r for r in records if r.criterion == crit), key=lambda r: r.final_value)
        warm = np.zeros(space.n_terms, dtype=bool)
        warm[[names.index(t) for t in best.terms]] = True
        out[crit] = certify_data(u, y, term_space=space, criterion=crit, warm_start=warm,
                                 time_limit=config.certify_time_limit).to_dict()
    return out


# -- summary --------------------------------------------------------------------------
