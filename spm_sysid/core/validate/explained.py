"""Whether the model explains the output at all: a warning when its fit is near the mean's.

A search always returns its best structure, even where no structure of the space
describes the output: a plant whose input acts through ``sin(2u)`` over several
periods, a record whose output is mostly noise, the wrong column given as the
input. The answer then holds a model that predicts little more than the output's
mean; its validation says so only as a fit percentage among many numbers. This
module turns that fit into a sentence where the user looks (the model's
``metadata.warnings``).

The fit is MATLAB's ``compare`` figure, ``100 (1 - ||y - yhat|| / ||y - mean(y)||)``
(:func:`~spm_sysid.core.validate.validation.metrics`), of the run the model was
chosen for: the free run with simulation focus, the one-step prediction
otherwise. Below :data:`LITTLE` percent the model's errors are over nine tenths
of the output's own spread (it explains under a fifth of the variance).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, MutableMapping

__all__ = ["IDENTIFIED", "LITTLE", "OPENING", "OTHER_DATA", "explained_warning",
           "set_explained_warning"]

#: Fit (percent) below which the model is said to explain little of the output.
LITTLE = 10.0

#: The warning's first words (how a later validation finds and replaces it).
OPENING = "the model explains little of the output"

#: What to do, after an identification ...
IDENTIFIED = ("the output is mostly noise, or it depends on the inputs in a way these terms "
              "do not describe (other lags, a dead time, a nonlinearity that is no "
              "low-degree polynomial, an input that is missing); check the signals given, "
              "and whether other lags, a larger --degree, a --delay or --regressors "
              "describe it")

#: ... and on other data than the model's own (``spm-sysid validate``).
OTHER_DATA = ("these data may visit ranges the model was not fitted on, or the system "
              "changed since; check the signals given, and identify a model on data like "
              "these")


def explained_warning(validation: Mapping, focus: str | None,
                      advice: str = IDENTIFIED) -> str | None:
    """The warning for a validation document whose focus run fits below LITTLE; else None.

    ``validation``: ``metadata["validation"]`` (``one_step``, ``free_run``, ``k_step``
    metrics and ``segment``). A run that diverged is reported elsewhere and an
    output that does not vary has no fit: neither gives a warning here.
    ``advice``: the sentence's end, what the user may do.
    """
    run, label = (("free_run", "free-run") if focus == "simulation"
                  else ("one_step", "one-step"))
    m = validation.get(run) or {}
    fit = m.get("fit_percent")
    if m.get("diverged_at") is not None or not isinstance(fit, (int, float)) \
            or not math.isfinite(fit) or fit >= LITTLE:
        return None
    where = validation.get("segment") or "validation"
    return (f"{OPENING}: its {label} fit on the {where} data is {round(fit, 1) + 0.0:.1f} % "
            f"(100 % is exact, 0 % no better than the output's mean): {advice}")


def set_explained_warning(metadata: MutableMapping, focus: str | None = None,
                          advice: str = IDENTIFIED, validation: Mapping | None = None
                          ) -> str | None:
    """Put the warning of ``metadata["validation"]`` into ``metadata["warnings"]``; return it.

    An earlier one (a validation replaced by a later one: the coupled run of
    several outputs, a model validated on other data) is taken out first;
    ``focus`` defaults to the metadata's, ``validation`` to its validation.
    """
    kept = [w for w in metadata.get("warnings") or [] if not str(w).startswith(OPENING)]
    found = explained_warning(metadata.get("validation") or {} if validation is None
                              else validation, focus or metadata.get("focus"), advice)
    if found:
        kept.append(found)
    if kept:
        metadata["warnings"] = kept
    else:
        metadata.pop("warnings", None)
    return found
