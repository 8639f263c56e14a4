"""Every tuning constant of the identification, in one place, each with its reason.

In the spirit of python-control's ``config.defaults``: the numbers that decide
how a structure is searched, judged, guarded and certified live here, not in the
modules that use them (those import them by name). Help texts that quote one
(the settings schema, warnings) are written from here too, so a number is
changed once. Settings a user chooses (the schema, :mod:`spm_sysid.core.settings`)
are not here: these are the engine's own.

Budgets are in work, not seconds, where a result should not depend on the
machine's speed (the polish counts structures scored); time limits are where a
user asked for one (``certify_time_limit``, ``job_timeout``).
"""

from __future__ import annotations

import numpy as np

# -- the data and the candidate matrix --------------------------------------------------

#: Rows per usable candidate term below which an in-sample criterion can overfit badly:
#: the data check warns, ``selection: auto`` validates, and no structure of more than
#: one term per this many rows is judged on held-out blocks.
ROWS_PER_TERM = 10

#: A model of more terms than one per ``ROWS_PER_TERM`` rows is warned about, and
#: validated selection judges no structure larger than this many terms either
#: (forward selection's path, the restarts of the certification's incumbent).
MAX_JUDGED_TERMS = 60

#: Relative eigenvalue below which an input's autocorrelation matrix is singular.
PE_TOL = 1e-8

#: Condition number of the unit-norm candidate matrix above which the data check warns.
CONDITION_WARN = 1e8

#: Spaces with more usable candidates skip the data check's collinearity scan (O(M^3)).
COLLINEAR_LIMIT = 600

#: A sample further from the median than this many 99th percentiles of the distances
#: is a glitch (a spike, a wrong unit, a bad read).
GLITCH_FACTOR = 50.0

#: The data check calls a record sampled K times faster than it moves when every input
#: and the output hold this share of their power below 1/(2K) of the sampling rate ...
OVERSAMPLED_POWER = 0.95

#: ... for the largest K of these (none: the check says nothing).
OVERSAMPLING_FACTORS = (10, 20, 50, 100)

#: Squared relative pivot below which a term is a combination of the others: a term
#: reproduced by the others to within a relative residual of about 3e-5.
RANK_TOL = 1e-9

#: SSE below which a fit is exact to rounding, relative to the target's norm squared:
#: exact fits then score alike and the fewest terms win.
SSE_FLOOR_RELATIVE = 1e3 * np.finfo(float).eps

# -- the search -------------------------------------------------------------------------

#: Structures the polish after the GA may score (a count, not seconds: the same seed
#: gives the same result on any machine).
POLISH_STRUCTURES = 50_000
#: Structures of more terms than this cost more to fit (about k^2): the polish of a
#: structure of k terms scores at most POLISH_STRUCTURES * (POLISH_TERMS / k)^2 of them,
#: so a large model's polish does not take many times its GA's time.
POLISH_TERMS = 20
#: Kicks of the iterated local search after the first local optimum (within the budget).
POLISH_KICKS = 1000
#: Terms a kick flips: from POLISH_FLIPS[0] to POLISH_FLIPS[1] - 1 (the GA's best and the
#: optimum typically differ in 8-11 terms when the GA misses: a kick must reach that far).
POLISH_FLIPS = (4, 12)
#: Neighbourhoods the polish ranks when it can rank them from the least-squares factor
#: (:class:`~spm_sysid.core.search.neighbourhood.MoveScreen`; criteria of the SSE and the
#: size): a count, as POLISH_STRUCTURES. One to two seconds at 84 candidates, up to
#: about 3 s at 120 (the polish reports its progress). 3 000 before 2026-12-04 (second
#: session): 6 000 reach the best known value on more GA seeds (docs/results.md).
POLISH_STEPS = 6000
#: Kicks in a row that do not improve the current structure before the polish restarts
#: from a larger kick of the best (POLISH_RESTART_FLIPS terms flipped), and restarts in a
#: row without a new best after which it stops. Measured at 84 candidates (robot arm,
#: dryer, heat exchanger; AIC, BIC; 20 GA seeds each; runs at the best value known):
#: kicks from the best only, 3 000 steps: 16/20/15/5/0/1 of 20; with the restarts
#: 18/20/19/6/0/5 (docs/results.md has the table).
POLISH_PATIENCE = 15
POLISH_RESTART_FLIPS = (8, 16)
POLISH_RESTARTS = 20
#: Descents in a row that lead back to the best structure itself, after which the polish
#: stops: every kick falls back into the best's basin (small spaces: the paper's 44
#: candidates, where the GA's best is usually the optimum).
POLISH_HOME = 30
#: The work of one ranked polish step (about (n + 1) k (n - k) for n candidate terms and
#: k in the structure) up to which the polish takes all POLISH_STEPS steps; beyond,
#: POLISH_STEPS x POLISH_STEP_WORK / work of them (a count, as the others): about 3 s at
#: most here. 454 candidates, a 100-term structure: about 110 steps, 2 s. Until the
#: second session of 2026-12-04 spaces of more than 120 terms kept the polish that
#: counts structures, which did almost nothing there (docs/results.md).
POLISH_STEP_WORK = 300_000

#: Bytes of ``[P y]`` rows the evaluator's numbers are built from at a time: a record of
#: more rows is reduced slice by slice, so that no copy of its candidate matrix is made
#: (one slice gives exactly the numbers of one pass).
FACTOR_SLICE_BYTES = 64 << 20

#: Bytes of one structure's columns (and target) a least-squares fit reads at a time
#: (:func:`~spm_sysid.core.fit.lstsq.structure_fit`). A one-pass fit holds about five
#: copies of them (selected, unit-norm, QR's own and Q); a longer record is fitted slice
#: by slice: 10^6 rows of seven terms held 270 MB in fits, 80 MB now. Records of fewer
#: rows (the robot arm, Silverbox's structures up to 30 terms) fit in one pass as before.
STRUCTURE_SLICE_BYTES = 16 << 20

#: Bytes of the Jacobian (rows x outputs x every output's terms) the final joint
#: refinement of several outputs may hold; a longer record is refined on windows spread
#: over it of as many rows as fit. The two-link arm's 10^5 samples (74 MB) still use
#: every sample.
JOINT_JACOBIAN_BYTES = 128 << 20

#: Bytes of the Jacobian (rows x terms) a single output's final refinement, and the
#: free-run covariance of the model it returns, may hold; a longer record uses the
#: windows of :data:`JOINT_JACOBIAN_BYTES`'s rule, of as many rows as fit. The solver
#: holds two such arrays beside the output's candidate matrix: at 128 MB two outputs of
#: 10^6 samples (q2: 91 candidates, 728 MB) peaked at 1.38-1.50 GiB in that refinement.
FINAL_JACOBIAN_BYTES = 64 << 20

#: Bytes the outputs of a record may work in at once (candidate matrices and the slices
#: of their fits, ``fit.problem.working_bytes``) while they are identified side by side
#: (one thread each); beyond it they take turns. Two outputs of
#: 10^5 samples in a (9, 9, 2) space hold 561 MB each: side by side the two-link arm took
#: 6.5 GB before the matrices were built and reduced in slices, 1.8 GB after (issue 41's
#: bound is 1.5 GB); small records (4 000 samples: 22 MB each) still run side by side.
PARALLEL_OUTPUT_BYTES = 512 << 20

#: Spaces of at most this many usable terms are certified after the GA by default.
AUTO_CERTIFY_TERMS = 120

#: Spaces of more usable terms than this, on records that are not long, are searched
#: twice when the criterion's optimum is the answer (selection ``criterion``): a second
#: GA and polish from an independent seed stream, the better kept. At
#: 84 candidates ((3, 3, 3) with the constant, first halves, 20 seeds) one GA and
#: polish reached the best value known in 20 / 20 / 19 / 12 / 1 / 5 runs (robot arm,
#: dryer, heat exchanger; AIC, BIC), the better of two in 20 / 20 / 20 / 19 / 4 / 10,
#: at about twice the time (0.5-2 s a run). The paper's 44 candidates stay one search.
#: Since 2026-12-07 (fifth session) three more polished starts follow there (forward
#: selection's end, every term, the best ends' common terms; ``identify._greedy_polishes``).
RESTART_TERMS = 60

# -- uncertainty bands ---------------------------------------------------------------

#: Simulated values an output band keeps at most (rows x draws, 160 MB): a record of more
#: than 100 000 rows gets fewer coefficient draws, never fewer than MIN_BAND_DRAWS.
BAND_VALUES = 20_000_000
MIN_BAND_DRAWS = 40

# -- orders: auto ---------------------------------------------------------------------

#: Candidate terms a proposed space may have at most: the GA, the screening and the
#: certification stay quick, and orders and degree trade within it (order 10 of degree 3
#: is 1 771 terms; order 3 of degree 3, 84; order 7 of degree 2, 120). Records with
#: fewer than ROWS_PER_TERM rows per term get a smaller budget.
AUTO_MAX_TERMS = 120

#: Samples the proposal scans at most (the first of the longest segment): a scan's spaces
#: compare on them; a longer record adds little to the comparison and costs in proportion.
SCAN_ROWS = 15_000

#: Share of the scanned samples each space is fitted on in the simulation focus's scan;
#: its free run is judged on the rest.
SCAN_FIT_SHARE = 2 / 3

#: Spaces of the simulation focus's scan refined: the best of each degree by least
#: squares, and this many best overall (a refinement costs a second or two).
SCAN_REFINED = 4

#: A smaller space whose held-out free-run error is within this factor of the best's is
#: preferred (fewer candidates: a quicker search, less to overfit).
SCAN_TOLERANCE = 1.02

# -- choosing on held-out blocks ----------------------------------------------------------

#: Held-out blocks of validated selection (focus prediction).
FOLDS = 3

#: Blocks of the simulation focus, laid SIMULATION_REPEATS times (shifted): long blocks
#: judge long simulations, and a nonlinear structure must beat the linear ones on the
#: sub-blocks (9) by more than the noise of the comparison.
SIMULATION_FOLDS = 3
SIMULATION_REPEATS = 3

#: Structures judged on held-out blocks at most (the GA's best, a ladder of sizes and
#: forward selection's path share them).
MAX_CANDIDATES = 60

#: Held-out rows a block must have to be judged on.
MIN_BLOCK_ROWS = 20

#: Each fold's rows must excite the linear terms at least this well, per row, as all rows
#: do: real records give 0.65-1.0 in contiguous blocks, a step test 0-0.07 (and
#: 0.21-0.35 in interleaved blocks).
MIN_FOLD_EXCITATION = 0.2

#: Directions of the linear terms the record excites at least this much (relative to the
#: most excited) are the ones each fold must see too.
EXCITED_DIRECTIONS = 1e-3

#: Blocks per fold tried, in turn, when contiguous blocks leave a fold without excitation.
INTERLEAVED_PIECES = (4, 8, 16, 32)

#: Structures within this many standard errors of the best held-out error count as
#: equally good; the one with the fewest terms among them is chosen.
ONE_SE = 1.0

#: A held-out error this many times the in-sample error is reported as overfitting.
OVERFIT_RATIO = 3.0

#: A nonlinear finalist replaces the best linear one only when a one-sided paired test
#: over the held-out blocks (log ratio of the two free-run MSEs per block) rejects "no
#: better" at this level: one test, so that many finalists cannot pass one by chance.
SIGNIFICANCE = 0.05

#: Other nonlinear finalists that also pass that test, tried in turn (by held-out error)
#: when the stability guard removes the tested one, before its shrunk version and before
#: the best linear one.
FALLBACKS = 3

# -- the simulation focus ---------------------------------------------------------------

#: Levenberg-Marquardt evaluations per move of the simulation-focused search and of the
#: in-sample screening (warm-started; the winner is refined to convergence).
SEARCH_STEPS = 30

#: Structure sizes judged on held-out blocks after the screening, and structures per size.
FINALISTS = 8
PER_SIZE = 2

#: Levenberg-Marquardt evaluations of a fold's fit (from least squares on its rows): 30
#: chose the same models as 100 on the robot arm, the dryer, the heat exchanger, the two
#: tanks and the two-link arm, at a third of the cost (the robot arm's simulation focus:
#: 10.0 s -> 5.3 s on a busy 2-core machine).
FOLD_STEPS = 30

#: Samples a screening or a fold's refinement fits on at most: longer records give it
#: REFINE_WINDOWS windows spread over them (each simulated from its own start). A
#: refinement costs about its samples times its terms squared per step; held-out
#: errors and the final refinement use every sample.
REFINE_ROWS = 5_000
REFINE_WINDOWS = 4

#: A record with more estimation rows than this is long: its held-out blocks (in a long
#: record each one holds thousands of samples, and a fit on the rest barely varies with
#: the block) are laid once, each cut into LONG_SUB_BLOCKS sub-blocks for the paired test
#: (SIMULATION_FOLDS * LONG_SUB_BLOCKS estimates, as repeats give a short record); one
#: finalist per size; a fold's refinement runs SEARCH_STEPS evaluations. The cost of the
#: judging then stays about that of a record of REFINE_ROWS samples.
LONG_ROWS = 20_000
LONG_SUB_BLOCKS = 3

#: On a long record: structures judged at most (instead of MAX_CANDIDATES), and the
#: Levenberg-Marquardt evaluations of the final refinement on every sample (from the
#: screening's coefficients, already refined on windows; instead of 200).
LONG_CANDIDATES = 60
LONG_FINAL_STEPS = 100

#: On a long record: moves (one term added or removed) from the best screened nonlinear
#: structure by its in-sample free-run criterion before the finalists are drawn. Silverbox
#: (65 062 samples, (3, 3, 3)): 3 moves bring the test part's free-run RMSE from 0.701 to
#: 0.619 mV, 8 moves to 0.616 (and cost 3x more).
LONG_POLISH_STEPS = 3

#: Levenberg-Marquardt evaluations of each of those moves (warm-started from the current
#: structure's coefficients: a term added starts at 0). On Silverbox 10 find the moves 30
#: find.
LONG_POLISH_EVALUATIONS = 10

#: Candidate terms of a space, at most, in which a move of the simulation search may
#: bring in any usable term (in larger spaces only the candidates' terms), and whose long
#: records get those moves: each move tries every term, warm-started, on the refinement
#: windows (Wiener-Hammerstein's
#: (7, 7, 2) space, 120 terms and a 59-term start: 225 s instead of 55 s, and a worse
#: model on the test part).
POLISH_SPACE = 100

#: The k of the k-step prediction that integrating or unstable records are judged on.
HORIZON = 10

#: A pole whose angle (radians) is below this counts as real (the open-loop check).
REAL_ANGLE = 0.05

#: A real pole up to 1 + this counts as an integrator, not an instability: least squares
#: puts the integrator of a positioning drive sampled at 1 kHz at 1.0005-1.001 (noise,
#: friction); an unstable real pole that slow (a time constant of 500 samples or more)
#: still simulates over a held-out block.
INTEGRATOR_MARGIN = 2e-3

#: Where a refinement whose least-squares start is unstable starts again, when its first
#: try ends unstable or diverging and the poles outside the circle are an integrator's
#: (real, positive): the start's poles scaled so that the largest lies at this radius
#: (:func:`~spm_sysid.core.fit.refine.stabilised_start`). At 1 kHz a drive's integrator
#: then starts with a time constant of 1 000 samples, and the refinement, guarded, moves it.
STABLE_START_RADIUS = 0.999

#: The open-loop check's ARX order at least (the output's lags when more, up to 10): an
#: ARX of order 2 or 3 on a drive at 1 kHz with friction puts its integrator at
#: 1.002-1.005 (equation-error bias), order 4 at 1.001.
OPEN_LOOP_ORDER = 4

#: An unstable reading of the open-loop check is read again at this many higher orders;
#: one that reads stable there wins (a real instability reads at every order: a pole at
#: 1.05 or 1.014 behind feedback reads at orders 2 to 13; the robot arm reads 1.124 at
#: order 5 and 1.0071 at 6, and at most 0.9989 at 4 and 7 to 10).
OPEN_LOOP_CONFIRM = 3

#: A column whose part not explained by the columns before it is below this share of its
#: norm repeats them (the open-loop check drops it before it reads the poles).
DEPENDENT = 1e-9

# -- the stability guard ----------------------------------------------------------------

#: A stressed simulation may leave the measured output's range by this many spans.
STRESS_FACTOR = 2.0

#: Random-phase inputs per segment in the guard (fixed seed: a selection is repeatable).
SURROGATES = 4

#: Factors the nonlinear coefficients are scaled by, in turn, when a structure fails the
#: guard (the linear ones kept: they carry the dynamics).
SHRINK_FACTORS = (0.5, 0.25, 0.1)

#: A free run leaves the measured output's range by this many spans: it diverged.
DIVERGENCE_FACTOR = 10.0

# -- several outputs --------------------------------------------------------------------

#: Held-out blocks of the coupled judgement, and Levenberg-Marquardt evaluations of a
#: fold's joint refinement.
COUPLED_FOLDS = 6
JOINT_FOLD_STEPS = 30

#: A joint refinement of structures with regressors (a finite-difference Jacobian: one
#: coupled run per coefficient) runs only while (coefficients + 1) x samples x outputs
#: stays within this: about 10 s a step at the measured 5 us per simulated sample.
JOINT_DIFFERENCE_SAMPLES = 2_000_000

#: A joint refinement steps only along the directions the record identifies: the
#: singular vectors of the start's Jacobian (columns scaled to unit norm) whose
#: singular value is at least ``JOINT_RCOND`` times the largest, or onto which the
#: start's residuals project by more than ``JOINT_SIGNIFICANCE`` standard
#: deviations of white noise of their spread. On the two-link arm, whose torques
#: excite few of their lags, free steps grew held-out errors 2-8x.
JOINT_RCOND = 1e-2
JOINT_SIGNIFICANCE = 3.0

# -- uncertainty ------------------------------------------------------------------------

#: Confidence level of the intervals and bands.
LEVEL = 0.95
