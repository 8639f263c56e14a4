"""The linter runs as a test, as ROS packages ship theirs."""

import shutil
import subprocess
import sys

import pytest

from .conftest import ROOT


def test_ruff_is_clean():
    ruff = shutil.which("ruff") or str(ROOT / ".venv" / "bin" / "ruff")
    if not shutil.which(ruff):
        pytest.skip("ruff not installed")
    r = subprocess.run([ruff, "check", "."], cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr


def test_core_imports_without_ros():
    code = ("import sys, spm_sysid, spm_sysid.core.identify, spm_sysid.tools.cli;"
            "assert 'rclpy' not in sys.modules, 'core pulled in rclpy'")
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr


def _slug(heading: str) -> str:
    """GitHub's anchor of a Markdown heading: lower case, punctuation dropped, - for spaces."""
    import re

    text = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return text.replace(" ", "-")


def test_every_link_between_the_docs_names_a_file_and_a_heading_that_exist():
    import re

    files = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
    anchors = {}
    for f in files:
        text = re.sub(r"```.*?```", "", f.read_text(), flags=re.S)
        anchors[f.resolve()] = {_slug(h) for h in re.findall(r"^#+ (.+)$", text, re.M)}
    broken = []
    for f in files:
        text = re.sub(r"```.*?```", "", f.read_text(), flags=re.S)
        text = re.sub(r"`[^`\n]*`", "", text)  # code is not a link
        for target in re.findall(r"\]\(([^)\s]+)\)", text):
            if target.startswith(("http:", "https:", "mailto:")):
                continue
            path, _, anchor = target.partition("#")
            dest = (f.parent / path).resolve() if path else f.resolve()
            if not dest.exists():
                broken.append(f"{f.name}: {target} (no such file)")
            elif anchor and dest.suffix == ".md" and anchor not in anchors.get(dest, set()):
                broken.append(f"{f.name}: {target} (no such heading)")
    assert not broken, broken


@pytest.mark.slow
def test_every_test_the_slow_list_names_exists():
    """A renamed test would silently leave the slow list and slow the quick selection."""
    from .conftest import slow_test_ids

    listed = slow_test_ids()
    assert len(listed) > 20
    files = sorted({i.split("::")[0] for i in listed})
    r = subprocess.run([sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:xdist",
                        *files], cwd=ROOT, capture_output=True, text=True, timeout=240)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr
    collected = {line.strip() for line in r.stdout.splitlines() if "::" in line}
    assert listed <= collected, sorted(listed - collected)
