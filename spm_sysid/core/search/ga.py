"""Genetic algorithm with single parent mating (SPM) for NARX structure selection.

A chromosome is one bit per candidate term, in the order of
:attr:`spm_sysid.core.model.terms.TermSpace.terms` (1 = term present). One generation,
as in section 2 of the paper:

1. score the population with the criterion (lower is better);
2. roulette-wheel selection fills a mating pool of the population's size;
3. **SPM**: the first ``round(s * P)`` parents of the (randomly ordered) pool are
   copied with every bit inverted, and each is crossed with its own inverse,
   giving ``2 * round(s * P)`` children; ``s = 0`` is the plain GA;
4. the rest of the pool is paired in order and crossed normally, giving the
   remaining children;
5. every pair is crossed at one random point with probability ``crossover_prob``
   (otherwise the children are copies of the parents); every child bit then
   flips with probability ``mutation_prob``;
6. elitism: the best chromosome of the generation replaces one child, unchanged.

Fitness for the roulette wheel (a design choice, since criteria are minimised
and may be negative; ``GAConfig.fitness``, see :func:`roulette_fitness`):

* ``akaike`` (the default): Akaike weights, ``F_i = exp(-(f_i - f_best) / 2)``;
* ``rank``: ``F_i`` = population size minus the rank of ``f_i``;
* ``window``: windowing, ``F_i = (f_worst - f_i) + 0.01 (f_worst - f_best)``.

All are shift-invariant (AIC of -10744 and of +5 behave alike); structures with
an infinite score (empty or rank-deficient) get zero fitness; when no score is
finite, selection is uniform.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field

import numpy as np

from ..fit.evaluator import structure_keys
from ..settings import SETTINGS, check_all

__all__ = [
    "FITNESS_TRANSFORMS",
    "GAConfig",
    "GAResult",
    "GenerationStats",
    "crossover",
    "mutate",
    "roulette_fitness",
    "roulette_select",
    "run_ga",
    "spm_mating",
]


#: Roulette-wheel fitness transforms (see :func:`roulette_fitness`).
FITNESS_TRANSFORMS = SETTINGS["fitness"].choices


@dataclass(frozen=True)
class GAConfig:
    """GA settings; defaults are the paper's.

    Parameters
    ----------
    population_size : int
        Chromosomes per generation (paper: 200 and 100).
    generations : int
        Number of reproduction steps (paper: 300).
    crossover_prob : float
        Probability that a pair is crossed (single point; paper: 0.6).
    mutation_prob : float
        Per-bit flip probability (paper: 0.01).
    spm_fraction : float
        Fraction s of the mating pool mated with its own inverse, 0 <= s <= 0.5
        (paper: 0 and 0.15).
    elitism : bool
        Carry the best chromosome unchanged into the next generation.
    init_terms : float
        Expected number of terms in a random initial structure: each of the M
        candidate terms is present with probability ``min(0.5, init_terms / M)``
        (the paper's 0.5 on its 44 terms; about 22 terms in any larger space, where
        half of all candidates would make every initial model huge).
    mutation_per_structure : float
        Ceiling on the expected bit flips per child: the per-bit rate is
        ``min(mutation_prob, mutation_per_structure / M)`` (the paper's 0.01 on 44
        terms; in 2000 terms 0.01 would flip 20 bits of every child).
    fitness : str
        Roulette fitness transform: ``akaike`` (default), ``rank`` or ``window``.

    Ranges and choices are those of the settings schema
    (:mod:`spm_sysid.core.settings`), checked on construction.
    """

    population_size: int = 200
    generations: int = 300
    crossover_prob: float = 0.6
    mutation_prob: float = 0.01
    spm_fraction: float = 0.15
    elitism: bool = True
    init_terms: float = 22.0
    mutation_per_structure: float = 0.44
    fitness: str = "akaike"

    def __post_init__(self) -> None:
        # ranges, types and choices are declared once, in the settings schema
        for name, value in check_all(asdict(self)).items():
            object.__setattr__(self, name, value)

    def rates(self, n_terms: int) -> tuple[float, float]:
        """Initial-term probability and per-bit mutation rate for ``n_terms`` candidates."""
        n = max(1, int(n_terms))
        return (min(0.5, self.init_terms / n),
                min(self.mutation_prob, self.mutation_per_structure / n))

    def to_dict(self) -> dict:
        """Plain-data form for JSON documents."""
        return asdict(self)


@dataclass(frozen=True)
class GenerationStats:
    """What one generation looked like (one entry of the history)."""

    generation: int
    best: float
    mean: float
    distinct: int
    evaluations: int
    elapsed: float


@dataclass
class GAResult:
    """Outcome of one GA run.

    Attributes
    ----------
    best_mask : ndarray of bool, shape (n_terms,)
    best_score : float
    first_best_generation : int
        Generation at which the final best structure was first in the population.
    history : list of GenerationStats
        Entry g describes population g (0 = the random initial one).
    evaluations, lookups : int
        Structures fitted and structures asked for.
    elapsed : float
        Wall-clock seconds.
    stopped_early : bool
        True when the progress callback asked to stop.
    """

    best_mask: np.ndarray
    best_score: float
    first_best_generation: int
    history: list[GenerationStats] = field(default_factory=list)
    evaluations: int = 0
    lookups: int = 0
    elapsed: float = 0.0
    stopped_early: bool = False

    @property
    def cache_hit_rate(self) -> float:
        """Fraction of structure look-ups answered without a fit."""
        return 1.0 - self.evaluations / self.lookups if self.lookups else 0.0

    def history_array(self, name: str) -> np.ndarray:
        """One field of the history as an array, e.g. ``history_array('best')``."""
        return np.array([getattr(h, name) for h in self.history])


# -- operators (pure functions of their inputs and the generator) -------------------


def roulette_fitness(scores: np.ndarray, kind: str = "akaike") -> np.ndarray:
    """Positive roulette-wheel fitness from minimised scores (see the module doc).

    Raises
    ------
    ValueError
        For a ``kind`` not in :data:`FITNESS_TRANSFORMS`.
    """
    if kind not in FITNESS_TRANSFORMS:
        raise ValueError(f"fitness must be one of {', '.join(FITNESS_TRANSFORMS)}, got {kind!r}")
    scores = np.asarray(scores, dtype=float)
    finite = np.isfinite(scores)
    if not finite.any():
        return np.ones_like(scores)
    worst, best = scores[finite].max(), scores[finite].min()
    if kind == "akaike":
        return np.where(finite, np.exp(-(np.where(finite, scores, best) - best) / 2.0), 0.0)
    if kind == "rank":
        order = np.argsort(np.where(finite, scores, np.inf), kind="stable")
        ranks = np.empty(len(scores))
        ranks[order] = np.arange(len(scores))
        return np.where(finite, len(scores) - ranks, 0.0)
    span = worst - best
    if span == 0:
        return finite.astype(float)
    return np.where(finite, (worst - np.where(finite, scores, worst)) + 0.01 * span, 0.0)


def roulette_select(fitness: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """Indices of ``n`` draws with probability proportional to ``fitness``."""
    cum = np.cumsum(fitness)
    return np.searchsorted(cum, rng.random(n) * cum[-1], side="right").clip(0, len(fitness) - 1)


def crossover(
    a: np.ndarray, b: np.ndarray, prob: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Single-point crossover of parent rows ``a[i]`` and ``b[i]``.

    Each pair is crossed with probability ``prob`` at a point c in 1..L-1: child 1
    takes a's bits before c and b's after, child 2 the opposite. Uncrossed pairs
    give copies of their parents.
    """
    n, length = a.shape
    cut = rng.integers(1, length, size=n) if length > 1 else np.ones(n, dtype=int)
    cut = np.where(rng.random(n) < prob, cut, length)
    take_a = np.arange(length)[None, :] < cut[:, None]
    return np.where(take_a, a, b), np.where(take_a, b, a)


def mutate(pop: np.ndarray, prob: float, rng: np.random.Generator) -> np.ndarray:
    """Flip every bit independently with probability ``prob``."""
    return pop ^ (rng.random(pop.shape) < prob)


def spm_mating(
    pool: np.ndarray, n_children: int, spm_fraction: float, config: GAConfig,
    rng: np.random.Generator,
) -> np.ndarray:
    """Children of a mating pool with single parent mating.

    The first ``round(spm_fraction * len(pool))`` parents are each crossed with
    their own bit-inverse (two children per parent); the remaining children come
    from crossing consecutive pairs of the rest of the pool.
    """
    n_spm = int(round(spm_fraction * len(pool)))
    n_spm = min(n_spm, n_children // 2)
    single = pool[:n_spm]
    c1, c2 = crossover(single, ~single, config.crossover_prob, rng)
    rest = pool[n_spm:]
    n_rest = n_children - 2 * n_spm
    n_pairs = (n_rest + 1) // 2
    if 2 * n_pairs > len(rest):  # only with tiny pools: reuse parents cyclically
        rest = np.resize(rest, (2 * n_pairs, pool.shape[1]))
    d1, d2 = crossover(rest[0 : 2 * n_pairs : 2], rest[1 : 2 * n_pairs : 2],
                       config.crossover_prob, rng)
    normal = np.empty((2 * n_pairs, pool.shape[1]), dtype=bool)
    normal[0::2], normal[1::2] = d1, d2
    return np.concatenate([c1, c2, normal[:n_rest]])


# -- the run --------------------------------------------------------------------------


class _Scorer:
    """What run_ga needs of an evaluator (see StructureEvaluator)."""

    n_terms: int
    evaluations: int
    lookups: int

    def score(self, masks: np.ndarray, keys: np.ndarray | None = None) -> np.ndarray: ...


def run_ga(evaluator: _Scorer, config: GAConfig | None = None,
           seed: int | np.random.SeedSequence | None = None,
           callback: Callable[[GenerationStats], bool | None] | None = None) -> GAResult:
    """Search structures with the GA; return the best one found.

    Parameters
    ----------
    evaluator : StructureEvaluator or NaiveEvaluator
        Scores a (B, n_terms) boolean population; lower is better.
    config : GAConfig
        Settings (defaults: the paper's).
    seed : int or numpy.random.SeedSequence, optional
        Seed of the random generator; the same seed gives the same run.
    callback : callable, optional
        Called with each generation's :class:`GenerationStats`; returning
        ``False`` stops the run after that generation.
    """
    config = config or GAConfig()
    rng = np.random.default_rng(seed)
    size, length = config.population_size, evaluator.n_terms
    start = time.perf_counter()
    evals0, lookups0 = evaluator.evaluations, evaluator.lookups

    init_prob, mutation = config.rates(length)
    pop, scores = _feasible_start(rng.random((size, length)) < init_prob, evaluator,
                                  init_prob, rng)
    result = GAResult(best_mask=pop[0].copy(), best_score=np.inf, first_best_generation=0)
    best_key: bytes | None = None
    for gen in range(config.generations + 1):
        keys = structure_keys(pop)
        if gen:  # the first population's scores come with it
            scores = evaluator.score(pop, keys)
        i_best = int(np.argmin(scores))
        if scores[i_best] < result.best_score or best_key is None:
            result.best_score = float(scores[i_best])
            result.best_mask = pop[i_best].copy()
            result.first_best_generation = gen
            best_key = result.best_mask.tobytes()
        finite = scores[np.isfinite(scores)]
        stats = GenerationStats(
            generation=gen,
            best=result.best_score,
            mean=float(finite.mean()) if finite.size else float("inf"),
            distinct=len(np.unique(keys)),
            evaluations=evaluator.evaluations - evals0,
            elapsed=time.perf_counter() - start,
        )
        result.history.append(stats)
        if callback is not None and callback(stats) is False:
            result.stopped_early = gen < config.generations
            break
        if gen == config.generations:
            break
        pop = _next_generation(pop, scores, result.best_mask, config, mutation, rng)

    result.evaluations = evaluator.evaluations - evals0
    result.lookups = evaluator.lookups - lookups0
    result.elapsed = time.perf_counter() - start
    return result


def _feasible_start(pop: np.ndarray, evaluator, init_prob: float,
                    rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """The first population, drawn again at half the density while no structure can be fitted.

    A record with exact dependencies among its candidates (a noise-free step test,
    a two-level input) can make every structure of the first draw rank-deficient;
    the selection then has nothing to prefer and the search never starts. Smaller
    structures hold fewer dependencies. A draw with one structure that fits is
    kept as it is. Returns the population and its scores.
    """
    size, length = pop.shape
    scores = evaluator.score(pop, structure_keys(pop))
    while not np.isfinite(scores).any() and init_prob * length >= 1.0:
        init_prob /= 2.0
        pop = rng.random((size, length)) < init_prob
        scores = evaluator.score(pop, structure_keys(pop))
    return pop, scores


def _next_generation(pop: np.ndarray, scores: np.ndarray, best: np.ndarray, config: GAConfig,
                     mutation: float, rng: np.random.Generator) -> np.ndarray:
    """Roulette selection, SPM mating, mutation; the best kept first with elitism."""
    size = len(pop)
    pool = pop[roulette_select(roulette_fitness(scores, config.fitness), size, rng)]
    n_children = size - 1 if config.elitism else size
    children = mutate(spm_mating(pool, n_children, config.spm_fraction, config, rng),
                      mutation, rng)
    return np.concatenate([best[None, :], children]) if config.elitism else children
