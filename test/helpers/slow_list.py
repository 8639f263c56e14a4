"""Write test/slow_tests.txt from pytest's ``--durations=0`` report (``make test-durations``).

Reads the report on stdin and lists every test whose setup, call and teardown
together took at least ``--threshold`` seconds (default 2.5: the quick selection,
``make test-quick``, then runs in about 2 minutes on two cores). The list marks
those tests ``slow`` (test/conftest.py); a test marked in its own code stays so.
"""

from __future__ import annotations

import argparse
import re
import sys
from collections import defaultdict
from pathlib import Path

LINE = re.compile(r"^(\d+(?:\.\d+)?)s (?:setup|call|teardown)\s+(\S.*)$")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--threshold", type=float, default=2.5)
    p.add_argument("--output", type=Path,
                   default=Path(__file__).resolve().parents[1] / "slow_tests.txt")
    args = p.parse_args()
    seconds: dict[str, float] = defaultdict(float)
    for line in sys.stdin:
        m = LINE.match(line.rstrip("\n"))
        if m:
            seconds[m.group(2)] += float(m.group(1))
    if not seconds:
        sys.exit("no durations on stdin: run pytest with --durations=0 -vv")
    slow = sorted((s, n) for n, s in seconds.items() if s >= args.threshold)
    text = ("# tests marked slow (test/conftest.py): seconds under `pytest -n 3` on two cores,\n"
            f"# at least {args.threshold:g} s; remade by `make test-durations`\n")
    text += "".join(f"{s:.1f}\t{n}\n" for s, n in reversed(slow))
    args.output.write_text(text)
    print(f"{len(slow)} of {len(seconds)} tests at least {args.threshold:g} s: {args.output}")


if __name__ == "__main__":
    main()
