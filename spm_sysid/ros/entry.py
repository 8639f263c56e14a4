"""Console entry points of the ROS executables (``ros2 run spm_sysid sysid_node``).

The node's module loads the compiled kernels as it is imported; when numba is
missing or broken, that is one clear error line and exit status 1 here, never
a traceback.
"""

from __future__ import annotations

import sys

from ..core.errors import MissingDependencyError

__all__ = ["sysid_node"]


def sysid_node(args: list[str] | None = None) -> int:
    """``sysid_node``: :func:`spm_sysid.ros.sysid_node.main`."""
    try:
        from .sysid_node import main
    except MissingDependencyError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    return main(args)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(sysid_node())
