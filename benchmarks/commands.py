"""``python -m benchmarks.commands bench`` (``make bench``) and ``... bench-sizes``.

``bench``: the engine against a naive evaluator; ``bench-sizes``: time and
memory against sizes. The benchmarks live beside the package, not in it: the
user's ``spm-sysid`` never imports them.
"""

from __future__ import annotations

from spm_sysid.tools.cli.common import add_schema_options

__all__ = ["add_parsers", "main"]


def cmd_bench(args) -> int:
    from spm_sysid.core.record import DataSpec, load_record
    from spm_sysid.tools.cli.common import job_settings

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


def main(argv: list[str] | None = None) -> int:
    """Run ``bench`` or ``bench-sizes`` (the options as ``spm-sysid identify``'s)."""
    from spm_sysid.tools.cli import run
    from spm_sysid.tools.cli.common import Parser

    parser = Parser(prog="python -m benchmarks.commands",
                    description="the engine's benchmarks (figures, no assertions)")
    add_parsers(parser.add_subparsers(dest="command", required=True, parser_class=Parser))
    return run(parser, argv)


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


if __name__ == "__main__":  # pragma: no cover
    import sys

    sys.exit(main())
