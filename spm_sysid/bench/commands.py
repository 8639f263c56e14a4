"""Benchmark commands of ``spm-sysid``: ``bench`` and ``bench-sizes``.

``bench``: the engine against a naive evaluator; ``bench-sizes``: time and
memory against sizes.

Registered by :mod:`spm_sysid.apps.main` (benchmarks sit above the tools).
"""

from __future__ import annotations

from ..tools.cli.common import add_schema_options

__all__ = ["add_parsers"]


def cmd_bench(args) -> int:
    from ..core.record import DataSpec, load_record
    from ..tools.cli.common import job_settings
    from .engine import run_benchmark, run_simulation_benchmark

    settings = job_settings(args)
    record = load_record(DataSpec.from_values({}, data=args.data))
    run_benchmark(record.u, record.y, criterion=settings.criterion, repeats=args.repeats,
                  naive_repeats=args.naive_repeats, config=settings.ga)
    run_simulation_benchmark(record.u, record.y, repeats=args.repeats, config=settings.ga)
    return 0


def cmd_bench_sizes(args) -> int:
    from .sizes import run

    return run(args)


def add_parsers(sub) -> None:
    """Register ``bench`` and ``bench-sizes``."""
    from .sizes import add_options as bench_sizes_options

    p = sub.add_parser("bench", help="time the engine against a naive evaluator")
    p.add_argument("--data", metavar="PATH")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--naive-repeats", type=int, default=3)
    add_schema_options(p, ("ga", "criterion"))
    p.set_defaults(func=cmd_bench)

    p = sub.add_parser("bench-sizes",
                       help="GA time and memory against term-space size and samples")
    bench_sizes_options(p)
    p.set_defaults(func=cmd_bench_sizes)
