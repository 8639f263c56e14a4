"""Console entry points of the ROS executables (``ros2 run spm_sysid sysid_node``).

The node checks at start that its compiled kernels can run (the ahead-of-time
build, else numba); when they cannot, that is one clear error line and exit
status 1 here, never a traceback; so are messages that were never built
(``spm_sysid_interfaces``).
"""

from __future__ import annotations

import sys

from ..core.errors import MissingDependencyError

__all__ = ["sysid_node"]


def sysid_node(args: list[str] | None = None) -> int:
    """``sysid_node``: :func:`spm_sysid.ros.sysid_node.main`."""
    try:
        from ..core.compiled.aot import prefer_jit
        from ..core.compiled.registry import require_kernels
        from .sysid_node import main

        require_kernels()
        prefer_jit()  # kernels that release the GIL: callbacks go on during a fit
    except MissingDependencyError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    except ModuleNotFoundError as exc:
        if exc.name is None or not exc.name.startswith("spm_sysid_interfaces"):
            raise
        print("error: the node's messages, service and action (spm_sysid_interfaces) are not "
              "built: run `make setup` in the package, or `colcon build` in your workspace "
              "and source its install/setup.bash", file=sys.stderr)
        return 1
    return main(args)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(sysid_node())
