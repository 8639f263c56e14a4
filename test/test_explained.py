"""A model that explains little of its output says so in its warnings.

A plant whose input acts through ``sin(2u)`` over several periods got
``y(t) = -0.010u(t-1)`` from the command as typed, with a free-run fit of
-0.01 % among the validation's figures and no warning line. The validation's
fit of the run the model was chosen for (the free run with simulation focus,
the one-step prediction otherwise) below 10 % is now a warning.
"""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from spm_sysid.core.jobs import run_job
from spm_sysid.core.jobs.settings import JobSettings
from spm_sysid.core.model.mimo import read_model_document
from spm_sysid.core.record import Record
from spm_sysid.core.validate.explained import (
    LITTLE,
    OPENING,
    explained_warning,
    set_explained_warning,
)

from .helpers.signals import second_order, squared, through_sine

EXE = str(Path(sys.executable).with_name("spm-sysid"))


def _sine_plant(n: int, seed: int):
    """y(t) = 0.8 y(t-1) + sin(2 u(t-1)), u of std 2: no low-degree polynomial of u."""
    rng = np.random.default_rng(seed)
    u = 2.0 * rng.standard_normal(n)
    return u, through_sine(u) + 0.01 * rng.standard_normal(n)


def _quadratic_plant(n: int, seed: int):
    rng = np.random.default_rng(seed)
    u = rng.standard_normal(n)
    return u, second_order(u, squared(0.2)) + 0.01 * rng.standard_normal(n)


def _csv(path: Path, u, y) -> Path:
    np.savetxt(path, np.column_stack([u, y]), delimiter=",", header="u,y", comments="")
    return path


def _identify(data: Path, out: Path, *extra: str) -> tuple[str, dict]:
    r = subprocess.run([EXE, "identify", "--data", str(data), *extra, "--json", str(out)],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    return r.stdout, json.loads(out.read_text())


def _fit(y, yhat) -> float:
    """MATLAB's compare fit, computed here from the samples."""
    return 100 * (1 - np.linalg.norm(y - yhat) / np.linalg.norm(y - y.mean()))


def test_the_command_as_typed_warns_where_no_structure_describes_the_output(tmp_path):
    u, y = _sine_plant(5000, seed=1)
    out, doc = _identify(_csv(tmp_path / "sine.csv", u, y), tmp_path / "m.json",
                         "--focus", "simulation", "--orders", "auto")
    said = [w for w in doc["metadata"]["warnings"] if w.startswith(OPENING)]
    assert len(said) == 1 and f"warning: {said[0]}" in out
    assert "free-run fit on the estimation data" in said[0]
    # the figure quoted is the model's free run on the record, computed here
    model, _ = read_model_document(tmp_path / "m.json")
    # (the run predicts the samples from the model's largest lag on)
    fit = _fit(y[model.term_space.max_lag:], model.simulate(u, y))
    assert fit < LITTLE
    assert f"is {round(fit, 1) + 0.0:.1f} %" in said[0]


def test_a_model_that_describes_its_output_gets_no_such_warning(tmp_path):
    u, y = _quadratic_plant(3000, seed=2)
    out, doc = _identify(_csv(tmp_path / "quad.csv", u, y), tmp_path / "m.json",
                         "--focus", "simulation", "--orders", "auto")
    assert OPENING not in out
    assert not any(w.startswith(OPENING) for w in doc["metadata"].get("warnings") or [])
    assert doc["metadata"]["validation"]["free_run"]["fit_percent"] > 90


def test_prediction_focus_judges_the_one_step_fit(tmp_path):
    """An output that is noise, unrelated to the input: no one-step prediction either."""
    rng = np.random.default_rng(4)
    u, y = rng.standard_normal(2000), rng.standard_normal(2000)
    out, doc = _identify(_csv(tmp_path / "noise.csv", u, y), tmp_path / "m.json")
    assert f"warning: {OPENING}: its one-step fit" in out
    # the sine plant's one-step prediction uses y(t-1): it explains a part
    u, y = _sine_plant(3000, seed=1)
    out, doc = _identify(_csv(tmp_path / "sine.csv", u, y), tmp_path / "m2.json")
    assert doc["metadata"]["validation"]["one_step"]["fit_percent"] > LITTLE
    assert OPENING not in out


def test_the_rule_on_validation_documents():
    def val(fit, diverged=None, segment="holdout"):
        return {"segment": segment, "one_step": {"fit_percent": 80.0, "diverged_at": None},
                "free_run": {"fit_percent": fit, "diverged_at": diverged}}

    assert explained_warning(val(LITTLE), "simulation") is None
    assert "free-run fit on the holdout data is 9.9 %" in explained_warning(val(9.9),
                                                                           "simulation")
    assert explained_warning(val(-250.0), "prediction") is None  # one-step 80 %
    assert explained_warning(val(None), "simulation") is None  # the output does not vary
    assert explained_warning(val(None, diverged=12), "simulation") is None  # said elsewhere
    meta = {"focus": "simulation", "validation": val(3.0), "warnings": ["other"]}
    set_explained_warning(meta)
    set_explained_warning(meta)
    assert meta["warnings"][0] == "other" and len(meta["warnings"]) == 2
    meta["validation"] = val(50.0)  # a later validation (the coupled run) replaces it
    set_explained_warning(meta)
    assert meta["warnings"] == ["other"]
    meta["warnings"] = [explained_warning(val(3.0), "simulation")]
    set_explained_warning(meta)
    assert "warnings" not in meta


def test_validate_on_other_data_warns_when_the_model_does_not_describe_them(tmp_path):
    """`spm-sysid validate MODEL --data FILE` as typed: the plant's own record, then another."""
    u, y = _quadratic_plant(3000, seed=2)
    _identify(_csv(tmp_path / "quad.csv", u, y), tmp_path / "m.json", "--focus", "simulation")
    u2, y2 = _quadratic_plant(3000, seed=3)
    rng = np.random.default_rng(3)
    for name, y_new, warned in (("same.csv", y2, False),
                                ("other.csv", rng.standard_normal(3000), True)):
        page = tmp_path / f"{name}.html"
        r = subprocess.run([EXE, "validate", str(tmp_path / "m.json"), "--data",
                            str(_csv(tmp_path / name, u2, y_new)), "--report", str(page)],
                           capture_output=True, text=True, timeout=120)
        assert r.returncode == 0, r.stderr
        said = [line for line in r.stdout.splitlines() if line.startswith(f"warning: {OPENING}")]
        assert len(said) == int(warned), r.stdout
        # the page's warnings say it too (the model file is left as it was)
        assert ("free-run fit on the supplied data" in page.read_text()) == warned
        if warned:
            assert "free-run fit on the supplied data" in said[0]
            assert "identify a model on data like these" in said[0]
    assert OPENING not in (tmp_path / "m.json").read_text()


def test_each_output_of_a_coupled_model_is_judged_on_the_coupled_run(tmp_path):
    """Two outputs: a plant, and noise that nothing drives: only the second warns.

    The same of ``spm-sysid validate`` on the coupled model's document.
    """
    u, y1 = _quadratic_plant(2000, seed=5)
    y2 = np.random.default_rng(6).standard_normal(2000)
    record = Record.from_samples(u, np.column_stack([y1, y2]), source="test",
                                 input_names=("u",), output_names=("a", "b"))
    settings = JobSettings.from_values({"ny": 2, "nu": 1, "degree": 2, "focus": "simulation",
                                        "generations": 20, "seed": 1})
    result = run_job(record, settings)
    warned = [any(w.startswith(OPENING) for w in m.metadata.get("warnings") or [])
              for m in result.model.models]
    assert warned == [False, True]
    assert result.model.models[1].metadata["validation"]["free_run_coupled"] is True
    result.model.save(tmp_path / "two.json")
    np.savetxt(tmp_path / "two.csv", np.column_stack([u, y1, y2]), delimiter=",",
               header="u,a,b", comments="")
    r = subprocess.run([EXE, "validate", str(tmp_path / "two.json"), "--data",
                        str(tmp_path / "two.csv"), "--output", "a,b"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    blocks = r.stdout.split("== output ")[1:]
    assert [f"warning: {OPENING}" in b for b in blocks] == [False, True]
