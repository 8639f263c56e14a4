"""`make run`: the main job end to end over real DDS, both foci."""

import subprocess
import sys

import pytest

from spm_sysid.core.model.narx import NarxModel

from .conftest import ROOT


@pytest.mark.slow
def test_make_run_pipeline_prints_both_foci(ros_env, tmp_path):
    # `make run` is `python -m spm_sysid.apps.pipeline --out out/run` in domain 61; here
    # the same defaults with the test's own domain and output places
    r = subprocess.run([sys.executable, "-m", "spm_sysid.apps.pipeline", "--out",
                        str(tmp_path / "run"), "--bag", str(tmp_path / "bag")],
                       capture_output=True, text=True, env=ros_env, timeout=300, cwd=ROOT)
    assert r.returncode == 0, r.stderr + r.stdout
    out = r.stdout
    assert "[4/7] sysid_node buffered 1024 paired samples" in out
    assert "~/identify (focus prediction, the paper's): y(t) = 3.158y(t-1)" in out
    assert "AIC -10744.78" in out and "free-run fit 11.1 %" in out
    # the node certifies by default (AIC, 44 terms, the criterion's choice)
    first = [ln for ln in out.splitlines() if "focus prediction, the paper's" in ln][0]
    assert "certified optimal over all structures" in first
    assert "~/identify (focus simulation):" in out
    sim = NarxModel.load(tmp_path / "run" / "model_simulation.json")
    assert sim.metadata["focus"] == "simulation"
    fit = sim.metadata["validation"]["free_run"]["fit_percent"]
    # validated selection: the structure the held-out blocks support (84.9 % in-sample)
    assert fit >= 84.0 and f"free-run fit {fit:.1f} %" in out
    assert NarxModel.load(tmp_path / "run" / "model.json").metadata["focus"] == "prediction"
    assert (tmp_path / "run" / "figures" / "model_simulation_free_run.png").exists()
