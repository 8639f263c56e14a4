"""Build ``spm_sysid_interfaces`` with colcon into this virtual environment.

``make setup`` (and so ``make run`` and ``make test``) runs this with the
environment's Python. The ROS 2 wheels from PyPI carry, in their CMake export
files, the include directories of the machine they were built on
(``/opt/python/cp311-cp311/...`` for Python and numpy); they are pointed at this
environment's own before colcon configures. The package is installed into the
environment's prefix (``--merge-install``): its libraries go to ``<venv>/lib``,
which the ROS wheels already put on the library path, and its Python modules to
the environment's site-packages. With a system ROS 2 (``/opt/ros/jazzy``) none of
this is needed: ``colcon build`` in a workspace builds both packages
(README, "ROS 2 workspace").

Run again, it does nothing unless the interface files changed (a stamp holds
their hash); ``--force`` rebuilds.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import re
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

HERE = Path(__file__).resolve().parent
PACKAGE = HERE / "spm_sysid_interfaces"
ROOT = HERE.parent
#: Include directories of the machine the wheels were built on.
BUILD_MACHINE = re.compile(r"/opt/python/cp3\d+-cp3\d+/(include/python3\.\d+|"
                           r"lib/python3\.\d+/site-packages/numpy/_core/include)")


def interface_hash() -> str:
    """Hash of the package's definition files (what a rebuild depends on)."""
    h = hashlib.sha256(sys.prefix.encode())
    for path in sorted(PACKAGE.rglob("*")):
        if path.is_file():
            h.update(str(path.relative_to(PACKAGE)).encode())
            h.update(path.read_bytes())
    return h.hexdigest()


def local_include(match: re.Match) -> str:
    if match.group(1).startswith("include"):
        return sysconfig.get_paths()["include"]
    import numpy

    return numpy.get_include()


def point_cmake_files_here(prefix: Path) -> int:
    """Replace the build machine's include directories in the wheels' CMake files."""
    changed = 0
    for path in prefix.glob("share/*/cmake/*.cmake"):
        text = path.read_text(errors="surrogateescape")
        new = BUILD_MACHINE.sub(local_include, text)
        if new != text:
            path.write_text(new, errors="surrogateescape")
            changed += 1
    return changed


def colcon_build(prefix: Path) -> None:
    colcon = shutil.which("colcon", path=str(prefix / "bin")) or shutil.which("colcon")
    if colcon is None:
        sys.exit("error: colcon is not installed in this environment "
                 "(pip install -e '.[ros,test]')")
    env = dict(os.environ)
    for var in ("AMENT_PREFIX_PATH", "CMAKE_PREFIX_PATH"):
        env[var] = os.pathsep.join(p for p in (str(prefix), env.get(var, "")) if p)
    env["PATH"] = os.pathsep.join([str(prefix / "bin"), env.get("PATH", "")])
    build = ROOT / "build" / "interfaces"
    cmd = [colcon, "--log-base", str(build / "log"), "build",
           "--base-paths", str(HERE), "--build-base", str(build),
           "--install-base", str(prefix), "--merge-install",
           "--cmake-args", f"-DPython3_EXECUTABLE={sys.executable}", "-DBUILD_TESTING=OFF"]
    r = subprocess.run(cmd, env=env, cwd=ROOT, capture_output=True, text=True)
    if r.returncode != 0:
        sys.stderr.write(r.stdout[-6000:] + r.stderr[-3000:])
        sys.exit(f"error: colcon could not build spm_sysid_interfaces (log in {build / 'log'})")


def importable() -> bool:
    """The generated messages import and construct (in a fresh process)."""
    probe = ("from spm_sysid_interfaces.msg import NarxModel; "
             "from spm_sysid_interfaces.action import Identify; "
             "from spm_sysid_interfaces.srv import GetModel; NarxModel(); Identify.Goal()")
    return subprocess.run([sys.executable, "-c", probe], cwd=ROOT,
                          capture_output=True).returncode == 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--force", action="store_true", help="rebuild even when up to date")
    args = parser.parse_args(argv)
    prefix = Path(sys.prefix)
    stamp = prefix / ".spm_sysid_interfaces"
    digest = interface_hash()
    if (not args.force and stamp.exists() and stamp.read_text().strip() == digest
            and importable()):
        print("spm_sysid_interfaces is up to date")
        return 0
    fixed = point_cmake_files_here(prefix)
    if fixed:
        print(f"pointed {fixed} CMake file(s) of the ROS wheels at this environment's "
              "Python and numpy include directories")
    print("building spm_sysid_interfaces with colcon (about a minute) ...", flush=True)
    colcon_build(prefix)
    if not importable():
        sys.exit("error: spm_sysid_interfaces was built but does not import")
    stamp.write_text(digest + "\n")
    print(f"spm_sysid_interfaces installed into {prefix}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
