"""The ``spm-sysid`` console script: the offline command line and ``call``.

``call`` is the one sub-command that needs ROS; it is added here, where tools
and ROS may meet, and imports rclpy only when it runs, so every other
sub-command works on machines without ROS. The benchmarks are not commands of
``spm-sysid``: they live beside the package (``benchmarks/``, ``make bench-*``).
"""

from __future__ import annotations

import sys
from pathlib import Path

from ..tools.cli import UserError, build_parser, run

__all__ = ["main"]


def _cmd_call(args) -> int:
    try:
        from .call import main as call_main
    except ImportError as exc:
        raise UserError(f"`call` needs ROS 2 (rclpy): {exc}") from None
    overrides = {}
    for item in args.set or []:
        name, sep, value = item.partition("=")
        if not sep or not name.strip():
            raise UserError(f"--set {item!r}: write NAME=VALUE, e.g. --set criterion=bic")
        overrides[name.strip()] = value
    bag = args.bag or ""
    if bag and Path(bag).exists():  # the node resolves a relative path from its own folder
        bag = str(Path(bag).resolve())
    return call_main(args.action, node_name=args.node, timeout=args.timeout,
                     show_model=args.show_model, overrides=overrides, bag_path=bag,
                     trigger=args.trigger, quiet=args.quiet, as_json=args.json)


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``spm-sysid``."""
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")  # argparse's subparsers
    p = sub.add_parser("call", help="ask a running sysid node to identify (its action: "
                       "progress, Ctrl-C cancels), to clear its buffer, or watch its "
                       "model's validity")
    p.add_argument("action", choices=("identify", "clear", "watch"),
                   help="identify; clear the buffer; watch: print ~/validity for --timeout "
                        "seconds (each change, else once a second)")
    p.add_argument("--node", default="/spm_sysid", help="node name (default /spm_sysid)")
    p.add_argument("--timeout", type=float, default=300.0,
                   help="seconds to wait (watch: seconds to watch)")
    p.add_argument("--show-model", action="store_true",
                   help="print the model after identify: equation, coefficients with "
                        "intervals, fits, certification")
    p.add_argument("--json", action="store_true",
                   help="with --show-model: print the model document (JSON) instead")
    p.add_argument("--set", action="append", metavar="NAME=VALUE",
                   help="override a setting for this identification only (repeatable), "
                   "e.g. --set criterion=bic --set generations=100")
    p.add_argument("--bag", help="identify on this bag (read by the node with its topics) "
                   "instead of the node's buffer")
    p.add_argument("--trigger", action="store_true",
                   help="use the std_srvs/Trigger service ~/identify instead of the action")
    p.add_argument("--quiet", action="store_true", help="no progress line")
    p.set_defaults(func=_cmd_call)
    return run(parser, argv)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
