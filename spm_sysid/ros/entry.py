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

SYSID_NODE_USAGE = """usage: sysid_node [--ros-args [-p NAME:=VALUE ...] [--params-file FILE]]

The spm_sysid node: records an input and an output topic into a buffer, identifies a
NARX model when asked (the ~/identify action or Trigger service), publishes it latched
on ~/model, ~/narx_model and ~/coefficients, then predicts every new sample and says
whether the model still holds (~/validity, /diagnostics). Ctrl-C ends it.

  sysid_node --ros-args --params-file config/sysid_node.yaml -p dashboard_port:=8765

Its parameters, with defaults and allowed values, are in config/sysid_node.yaml
(`spm-sysid settings --yaml` prints them, `spm-sysid settings` as a table); the
interface is in docs/ros_interface.md. Every process that starts ROS should set
ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST and its own ROS_DOMAIN_ID.
"""


def sysid_node(args: list[str] | None = None) -> int:
    """``sysid_node``: :func:`spm_sysid.ros.sysid_node.main`; ``--help`` prints the usage."""
    from .common import asks_for_help

    if asks_for_help(args):
        print(SYSID_NODE_USAGE, end="")
        return 0
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
