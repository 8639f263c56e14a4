"""The ``spm-sysid`` command line: one module per command family.

========================  ==================================================  ===========
command                   what it does                                        module
========================  ==================================================  ===========
``identify``              select and fit a model on data (the main job)       ``identify``
``certify``               prove the best structure of the space, or the gap   ``certify``
``validate``              validate a saved model on data                      ``validate``
``check-data``            can the data identify the space? (excitation ...)   ``checks``
``propose-lags``          propose lags and degree from the data               ``checks``
``compile``               compile the numeric kernels ahead                   ``checks``
``experiment``            the paper's study: SPM vs plain GA                  ``studies``
``batch``                 one model per input, here or on a Dask cluster      ``studies``
``make-bag``              a data file as a rosbag2 MCAP bag                   ``data``
``fetch-data``            download the robot-arm data                         ``data``
``settings``              every setting: default, allowed values, where       here
========================  ==================================================  ===========

:mod:`spm_sysid.apps.main` adds ``call`` (the ROS node's client); the benchmarks
live beside the package (``benchmarks/``). Shared pieces
(options from the settings schema, loading data, checking destinations) are in
:mod:`.common`, what identify and validate write in :mod:`.outputs`, progress bars in
:mod:`.progress`. Every failure a user can
cause ends with one ``error: ...`` line and exit status 2, never a traceback.
"""

from __future__ import annotations

import os

# Our matrices are small: one BLAS thread per process is fastest, and the experiment
# runner uses one process per core. Set before numpy is imported.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import sys  # noqa: E402

from ...core.errors import DataError, MissingDependencyError  # noqa: E402
from . import certify, checks, data, identify, studies, validate  # noqa: E402
from .common import Parser, UserError  # noqa: E402

__all__ = ["UserError", "build_parser", "main", "run"]


def cmd_settings(args) -> int:
    from ...core.settings import node_yaml, settings_table

    print(node_yaml() if args.yaml else settings_table(), end="")
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The argument parser (exposed for documentation and tests)."""
    from ... import __version__

    parser = Parser(
        prog="spm-sysid",
        description="Polynomial NARX identification with a single-parent-mating GA.",
    )
    parser.add_argument("--version", action="version", version=f"spm-sysid {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=Parser)
    identify.add_parser(sub)
    certify.add_parser(sub)
    validate.add_parser(sub)
    checks.add_parsers(sub)
    studies.add_parsers(sub)
    data.add_parsers(sub)
    p = sub.add_parser("settings", help="every setting: default, allowed values, where")
    p.add_argument("--yaml", action="store_true",
                   help="print the node's parameter file (config/sysid_node.yaml)")
    p.set_defaults(func=cmd_settings)
    return parser


def main(argv: list[str] | None = None) -> int:
    """The offline command line (every sub-command but ``call``, which needs ROS).

    The ``spm-sysid`` console script is :func:`spm_sysid.apps.main.main`: this
    parser plus ``call``.
    """
    return run(build_parser(), argv)


def _terminate_as_interrupt(signum, frame):
    raise KeyboardInterrupt


def run(parser: argparse.ArgumentParser, argv: list[str] | None = None) -> int:
    """Parse and run a sub-command; user errors become one ``error:`` line, status 2.

    SIGTERM (``timeout``, systemd, a job scheduler) is handled as Ctrl-C: work in
    progress stops, partial results stay, worker processes end; exit status 130.
    """
    import signal
    import threading

    args = parser.parse_args(argv)
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _terminate_as_interrupt)
    try:
        status = int(args.func(args) or 0)
        sys.stdout.flush()
        return status
    except BrokenPipeError:
        # the reader went away (e.g. `| head`): stop quietly, as command-line tools do
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 0
    except (UserError, DataError, ValueError, OSError, MissingDependencyError) as exc:
        print(f"error: {exc}", file=sys.stderr)  # ModelFormatError etc. are ValueErrors
        return 2
    except MemoryError:  # an allocation the machine refused (ulimit -v, a container)
        from ...core.memory import format_bytes, memory_limit

        limit, source = memory_limit()
        print(f"error: out of memory: the machine refused an allocation (the memory bound is "
              f"{format_bytes(limit)}, {source}); use fewer candidate terms or less data, or "
              "set SPM_SYSID_MAX_MEMORY to what this machine can give", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
