"""colcon builds the package; the installed sysid_node runs and offers its service."""

import pytest

pytest.importorskip("rclpy", reason="ROS 2 is not installed here (make test installs it)")

import os
import shutil
import subprocess
import sys

from .conftest import ROOT
from .ros_harness import Harness, stop

#: one worker runs this file (its module fixture is expensive to make twice); the build
#: alone may take up to BUILD_TIMEOUT on a busy machine, and the suite's 300 s per test
#: must not cut it short: this file's limit says so
BUILD_TIMEOUT = 900
pytestmark = [pytest.mark.ros, pytest.mark.slow, pytest.mark.xdist_group("colcon"),
              pytest.mark.timeout(BUILD_TIMEOUT + 300)]


@pytest.fixture(scope="module")
def workspace(tmp_path_factory):
    colcon = shutil.which("colcon") or str(ROOT / ".venv" / "bin" / "colcon")
    if not os.path.exists(colcon):
        pytest.skip("colcon is not installed")
    ws = tmp_path_factory.mktemp("ws")
    (ws / "src").mkdir()
    os.symlink(ROOT, ws / "src" / "spm_sysid")
    # the README's workspace command: both packages (colcon does not look for packages
    # inside the spm_sysid package's folder, so both are named); the ROS wheels of the
    # environment are the underlay, as /opt/ros/jazzy would be
    # (the README's lines for the wheels: the environment activated, both prefixes set)
    env = dict(os.environ, VIRTUAL_ENV=sys.prefix, AMENT_PREFIX_PATH=sys.prefix,
               CMAKE_PREFIX_PATH=sys.prefix)
    env["PATH"] = os.pathsep.join([os.path.join(sys.prefix, "bin"), env.get("PATH", "")])
    r = subprocess.run([colcon, "build", "--base-paths", "src/spm_sysid",
                        "src/spm_sysid/interfaces"],
                       cwd=ws, capture_output=True, text=True, timeout=BUILD_TIMEOUT, env=env)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    return ws


def _interfaces_import_from_the_workspace(workspace):
    pkg = workspace / "install" / "spm_sysid_interfaces"
    site = next((pkg / "lib").glob("python3*/site-packages"))
    assert (site / "spm_sysid_interfaces" / "action" / "_identify.py").exists()
    assert list((pkg / "lib").glob("libspm_sysid_interfaces__rosidl_typesupport_fastrtps_c.so"))
    env = dict(os.environ, PYTHONPATH=str(site),
               LD_LIBRARY_PATH=os.pathsep.join([str(pkg / "lib"),
                                                os.environ.get("LD_LIBRARY_PATH", "")]))
    probe = subprocess.run(
        [sys.executable, "-c", "import spm_sysid_interfaces.msg as m; "
         "print(m.__file__); print(m.NarxModel.CERTIFICATION_OPTIMAL)"],
        env=env, capture_output=True, text=True, cwd=workspace)
    assert probe.returncode == 0, probe.stderr
    assert probe.stdout.splitlines() == [str(site / "spm_sysid_interfaces" / "msg" /
                                             "__init__.py"), "1"]


def _install_tree(workspace):
    pkg = workspace / "install" / "spm_sysid"
    for exe in ("sysid_node", "bag_player"):
        path = pkg / "lib" / "spm_sysid" / exe
        assert path.is_file() and os.access(path, os.X_OK), exe
    assert (pkg / "share" / "ament_index" / "resource_index" / "packages" / "spm_sysid").exists()
    assert "<name>spm_sysid</name>" in (pkg / "share" / "spm_sysid" / "package.xml").read_text()
    assert (pkg / "share" / "spm_sysid" / "config" / "sysid_node.yaml").exists()
    site = next((pkg / "lib").glob("python3*/site-packages/spm_sysid/ros/sysid_node.py"))
    assert site.exists()


def _installed_node_offers_its_service(workspace, ros_env):
    pkg = workspace / "install" / "spm_sysid"
    site = next((pkg / "lib").glob("python3*/site-packages"))
    env = dict(ros_env)
    env["PYTHONPATH"] = os.pathsep.join([str(site), env.get("PYTHONPATH", "")])
    env["AMENT_PREFIX_PATH"] = os.pathsep.join([str(pkg), env.get("AMENT_PREFIX_PATH", "")])
    # where does the installed executable import the package from?
    probe = subprocess.run([sys.executable, "-c", "import spm_sysid; print(spm_sysid.__file__)"],
                           env=env, capture_output=True, text=True, cwd=workspace)
    assert probe.stdout.strip().startswith(str(site))
    node = subprocess.Popen([str(pkg / "lib" / "spm_sysid" / "sysid_node"), "--ros-args",
                             "-p", "min_samples:=10"], env=env, cwd=workspace,
                            stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT)
    harness = Harness(ros_env)
    try:
        harness.wait_ready()
        res = harness.call("/spm_sysid/identify")
        assert not res.success and "too few samples: 0 paired samples" in res.message
    finally:
        harness.close()
        stop(node)


def test_the_readme_workspace_build_installs_both_packages_and_the_node_runs(workspace,
                                                                           ros_env):
    """One test, so the workspace (about a minute of CMake) is built once per suite."""
    _interfaces_import_from_the_workspace(workspace)
    _install_tree(workspace)
    _installed_node_offers_its_service(workspace, ros_env)
