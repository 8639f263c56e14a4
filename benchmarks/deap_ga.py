"""The baseline a user would write: a plain DEAP genetic algorithm with numpy's lstsq.

``python -m benchmarks.deap_ga`` selects the robot-arm model's structure
in the paper's space (44 candidate terms) by AIC with the paper's GA settings
(population 200, 300 generations, one-point crossover 0.6, bit-flip mutation
0.01, roulette selection on the linearly scaled criterion, the best kept) and
prints the best structure. Every individual is fitted by
``numpy.linalg.lstsq`` on its columns: no cache, no shared factorisation. It
is the yardstick of ``python -m benchmarks.speed`` (needs the ``bench``
extra: ``pip install -e '.[bench]'``).
"""

from __future__ import annotations

import random
import sys

import numpy as np

__all__ = ["main"]


def main(argv: list[str] | None = None) -> int:
    from deap import base, creator, tools

    from spm_sysid.core.io.datasets import load_robot_arm
    from spm_sysid.core.model.terms import TermSpace

    u, y = load_robot_arm()
    ts = TermSpace()
    P, t = ts.regression_matrix(u, y), ts.target(y)
    n = len(t)

    def aic(individual) -> tuple[float]:
        cols = [i for i, bit in enumerate(individual) if bit]
        if not cols:
            return (float("inf"),)
        A = P[:, cols]
        theta, _, rank, _ = np.linalg.lstsq(A, t, rcond=None)
        if rank < len(cols):
            return (float("inf"),)
        r = t - A @ theta
        return (n * np.log(r @ r / n) + 2 * len(cols),)

    random.seed(1)
    if not hasattr(creator, "FitnessMin"):
        creator.create("FitnessMin", base.Fitness, weights=(-1.0,))
        creator.create("Individual", list, fitness=creator.FitnessMin)
    tb = base.Toolbox()
    tb.register("bit", random.random)
    tb.register("individual", tools.initRepeat, creator.Individual,
                lambda: random.random() < 0.5, ts.n_terms)
    tb.register("population", tools.initRepeat, list, tb.individual)
    tb.register("evaluate", aic)
    tb.register("mate", tools.cxOnePoint)
    tb.register("mutate", tools.mutFlipBit, indpb=0.01)

    def roulette(pop, k):
        values = np.array([ind.fitness.values[0] for ind in pop])
        finite = np.isfinite(values)
        worst, best = values[finite].max(), values[finite].min()
        weight = np.where(finite, worst - np.where(finite, values, worst) + 0.01 * (
            worst - best), 0.0)
        cum = np.cumsum(weight)
        return [pop[int(np.searchsorted(cum, random.random() * cum[-1], side="right"))]
                for _ in range(k)]

    pop = tb.population(n=200)
    for ind in pop:
        ind.fitness.values = tb.evaluate(ind)
    best = tools.selBest(pop, 1)[0]
    for _ in range(300):
        children = [tb.clone(ind) for ind in roulette(pop, len(pop) - 1)]
        for a, b in zip(children[::2], children[1::2]):
            if random.random() < 0.6:
                tb.mate(a, b)
        for c in children:
            tb.mutate(c)
            c.fitness.values = tb.evaluate(c)
        pop = [tb.clone(best)] + children
        best = tools.selBest(pop, 1)[0]
    names = ts.term_names()
    print(f"AIC {best.fitness.values[0]:.2f}: "
          + ", ".join(names[i] for i, bit in enumerate(best) if bit))
    return 0


if __name__ == "__main__":
    sys.exit(main())
