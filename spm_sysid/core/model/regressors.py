"""Regressors beside the polynomial terms: fixed functions of lagged signals.

A regressor is an expression such as ``sign(y(t-1)-y(t-2))`` (Coulomb
friction: the sign of the last step of the output) or ``abs(u(t-1))``. It is a
building block of the term space like a lagged signal: a candidate term is a
product of at most ``degree`` blocks, so ``sign(y(t-1)-y(t-2))`` is a term of
its own and ``sign(y(t-1)-y(t-2))*u(t-1)`` one of degree 2. The GA, the
polish and the certification select columns; a regressor is one more column,
and the certificate still holds.

The grammar (never ``eval``; anything else is one error line naming the token)::

    expr   := term (("+" | "-") term)*
    term   := unary (("*" | "/") unary)*        division by a number only
    unary  := "-" unary | atom
    atom   := NUMBER | SIGNAL "(" "t" ["-" INT] ")" | FUNC "(" expr {"," expr} ")"
            | "(" expr ")"

``SIGNAL`` is the output (lags of at least 1: the model stays causal) or an
input (lags of at least 0). ``FUNC`` is one of :data:`FUNCTIONS`:
``sign(x)`` (0 at 0), ``abs(x)``, ``tanh(x)``, ``min(a, b)``, ``max(a, b)``,
``sat(x, a)`` (x clipped to [-a, a]) and ``deadzone(x, w)`` (``sign(x) *
max(|x| - w, 0)``). Text of at most :data:`MAX_TEXT` characters and
:data:`MAX_DEPTH` levels of nesting.

An expression is kept in its canonical text (:func:`canonical`), which is
what model documents store: parsing it again gives the same expression. Named
sets (``friction``, ``saturation``) are expanded from the data in
:mod:`.presets`.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np

__all__ = ["FUNCTIONS", "MAX_DEPTH", "MAX_TEXT", "Expr", "Program", "RegressorError", "canonical",
           "evaluate", "parse", "program"]

#: Longest expression text, and deepest nesting.
MAX_TEXT = 200
MAX_DEPTH = 12

#: Functions and their number of arguments.
FUNCTIONS = {"sign": 1, "abs": 1, "tanh": 1, "min": 2, "max": 2, "sat": 2, "deadzone": 2}


class RegressorError(ValueError):
    """An expression the grammar does not accept (the message names the token)."""


@dataclass(frozen=True)
class Expr:
    """A node: ``op`` is ``num``, ``sig``, ``neg``, ``+ - * /`` or a function name."""

    op: str
    args: tuple = ()
    value: float = 0.0      # num
    signal: str = ""        # sig
    lag: int = 0            # sig

    def signals(self) -> set[tuple[str, int]]:
        """The lagged signals it reads, as (name, lag)."""
        if self.op == "sig":
            return {(self.signal, self.lag)}
        return set().union(*(a.signals() for a in self.args)) if self.args else set()


_TOKEN = re.compile(r"\s*(?:(\d+\.?\d*(?:[eE][+-]?\d+)?|\.\d+(?:[eE][+-]?\d+)?)|"
                    r"([A-Za-z_][A-Za-z0-9_]*)|(.))")


def _tokens(text: str) -> list[tuple[str, str]]:
    out = []
    pos = 0
    text = text.rstrip()
    while pos < len(text):
        m = _TOKEN.match(text, pos)
        num, name, other = m.groups()
        pos = m.end()
        if num is not None:
            out.append(("num", num))
        elif name is not None:
            out.append(("name", name))
        elif other is not None:  # refused where the parser reaches it (names come first)
            out.append(("op", other) if other in "+-*/()," else ("bad", other))
    return out


class _Parser:
    """Recursive descent over the tokens, with the signals known to the term space."""

    def __init__(self, text: str, output: str, inputs: tuple[str, ...]) -> None:
        self.text = text
        self.toks = _tokens(text)
        self.i = 0
        self.output, self.inputs = output, inputs
        self.depth = 0

    def peek(self) -> tuple[str, str] | None:
        return self.toks[self.i] if self.i < len(self.toks) else None

    def take(self, want: str | None = None) -> tuple[str, str]:
        tok = self.peek()
        if tok is not None and tok[0] == "bad":
            raise RegressorError(f"unexpected {tok[1]!r} in regressor {self.text!r} (allowed: "
                                 "lagged signals, numbers, + - * /, parentheses and "
                                 f"{', '.join(FUNCTIONS)})")
        if tok is None:
            raise RegressorError(f"regressor {self.text!r} ends early"
                                 + (f" (expected {want!r})" if want else ""))
        if want is not None and tok[1] != want:
            raise RegressorError(f"expected {want!r} in regressor {self.text!r}, found "
                                 f"{tok[1]!r}")
        self.i += 1
        return tok

    def parse(self) -> Expr:
        e = self.expr()
        if self.peek() is not None:
            raise RegressorError(f"unexpected {self.peek()[1]!r} in regressor {self.text!r}")
        return e

    def nested(self):
        self.depth += 1
        if self.depth > MAX_DEPTH:
            raise RegressorError(f"regressor nested deeper than {MAX_DEPTH} levels")

    def expr(self) -> Expr:
        self.nested()
        e = self.term()
        while self.peek() in (("op", "+"), ("op", "-")):
            op = self.take()[1]
            e = Expr(op, (e, self.term()))
        self.depth -= 1
        return e

    def term(self) -> Expr:
        e = self.unary()
        while self.peek() in (("op", "*"), ("op", "/")):
            op = self.take()[1]
            right = self.unary()
            if op == "/" and (right.op != "num" or right.value == 0.0):
                raise RegressorError(f"regressor {self.text!r} divides by something other "
                                     "than a non-zero number (divide by a scale only)")
            e = Expr(op, (e, right))
        return e

    def unary(self) -> Expr:
        if self.peek() == ("op", "-"):
            self.take()
            self.nested()
            e = Expr("neg", (self.unary(),))
            self.depth -= 1
            return e
        return self.atom()

    def atom(self) -> Expr:
        kind, tok = self.take()
        if kind == "num":
            value = float(tok)
            if not math.isfinite(value):
                raise RegressorError(f"number {tok!r} is not finite")
            return Expr("num", value=value)
        if kind == "op" and tok == "(":
            e = self.expr()
            self.take(")")
            return e
        if kind != "name":
            raise RegressorError(f"unexpected {tok!r} in regressor {self.text!r}")
        if tok in FUNCTIONS:
            self.take("(")
            args = [self.expr()]
            while self.peek() == ("op", ","):
                self.take()
                args.append(self.expr())
            self.take(")")
            if len(args) != FUNCTIONS[tok]:
                raise RegressorError(f"{tok} takes {FUNCTIONS[tok]} argument(s), got "
                                     f"{len(args)}")
            return Expr(tok, tuple(args))
        if tok == self.output or tok in self.inputs:
            return self.signal(tok)
        raise RegressorError(f"unknown name {tok!r} in regressor {self.text!r} (signals: "
                             f"{', '.join((self.output,) + tuple(self.inputs))}; functions: "
                             f"{', '.join(FUNCTIONS)})")

    def signal(self, name: str) -> Expr:
        self.take("(")
        kind, tok = self.take()
        if tok != "t":
            raise RegressorError(f"{name}({tok}...: a signal is read at t or t-k")
        lag = 0
        sign = self.peek()
        if sign == ("op", "+"):
            raise RegressorError(f"{name}(t+...) reads the future; use {name}(t-k)")
        if sign == ("op", "-"):
            self.take()
            k, num = self.take()
            if k != "num" or not num.isdigit():
                raise RegressorError(f"{name}(t-{num}): the lag must be a whole number")
            lag = int(num)
        self.take(")")
        if name == self.output and lag < 1:
            raise RegressorError(f"{name}(t) is the output being predicted; a regressor "
                                 f"reads {name}(t-1) or earlier")
        return Expr("sig", signal=name, lag=lag)


def parse(text: str, output: str = "y", inputs: tuple[str, ...] = ("u",)) -> Expr:
    """The expression of ``text`` over the signals ``output`` and ``inputs``.

    Raises
    ------
    RegressorError
        Text that is too long, nested too deep, or outside the grammar.
    """
    if not isinstance(text, str):
        raise RegressorError(f"a regressor is text, got {type(text).__name__}")
    if len(text) > MAX_TEXT:
        raise RegressorError(f"regressor of {len(text)} characters; at most {MAX_TEXT}")
    if not text.strip():
        raise RegressorError("empty regressor")
    return _Parser(text, output, tuple(inputs)).parse()


_PRECEDENCE = {"+": 1, "-": 1, "*": 2, "/": 2, "neg": 3}


def canonical(e: Expr) -> str:
    """The expression's text, parenthesised where needed: what documents store."""
    if e.op == "num":
        return repr(e.value) if e.value != int(e.value) or abs(e.value) >= 1e16 \
            else str(int(e.value))
    if e.op == "sig":
        return f"{e.signal}(t)" if e.lag == 0 else f"{e.signal}(t-{e.lag})"
    if e.op in FUNCTIONS:
        return f"{e.op}({','.join(canonical(a) for a in e.args)})"
    if e.op == "neg":
        inner = canonical(e.args[0])
        return f"-{inner}" if e.args[0].op in ("num", "sig") or e.args[0].op in FUNCTIONS \
            else f"-({inner})"
    left, right = (canonical(a) for a in e.args)
    p = _PRECEDENCE[e.op]
    if _PRECEDENCE.get(e.args[0].op, 9) < p:
        left = f"({left})"
    # the right side binds tighter: a-(b-c), a/(b*c)
    if _PRECEDENCE.get(e.args[1].op, 9) <= p:
        right = f"({right})"
    return f"{left}{e.op}{right}"


def evaluate(e: Expr, get) -> np.ndarray:
    """The expression on arrays: ``get(name, lag)`` gives a lagged signal's values."""
    if e.op == "num":
        return np.float64(e.value)
    if e.op == "sig":
        return get(e.signal, e.lag)
    args = [evaluate(x, get) for x in e.args]
    with np.errstate(over="ignore", invalid="ignore"):
        return _NUMPY[e.op](*args)


def _sat(x, a):
    lim = np.abs(a)
    return np.minimum(np.maximum(x, -lim), lim)


def _deadzone(x, w):
    return np.sign(x) * np.maximum(np.abs(x) - w, 0.0)


#: Each operation on arrays (what the kernels compute step by step).
_NUMPY = {"neg": np.negative, "+": np.add, "-": np.subtract, "*": np.multiply,
          "/": np.divide, "sign": np.sign, "abs": np.abs, "tanh": np.tanh, "min": np.minimum,
          "max": np.maximum, "sat": _sat, "deadzone": _deadzone}


# -- the compiled form ---------------------------------------------------------------------

#: Instruction codes of :class:`Program` (a stack machine the simulation kernels run).
OPS = {"y": 0, "u": 1, "num": 2, "+": 3, "-": 4, "*": 5, "/": 6, "neg": 7, "sign": 8,
       "abs": 9, "tanh": 10, "min": 11, "max": 12, "sat": 13, "deadzone": 14}


@dataclass(frozen=True)
class Program:
    """Regressors as postfix code: ``code`` (n, 3) int64 (op, a, b), ``start`` per regressor.

    ``y`` pushes ``y(t - a)``; ``u`` pushes input ``a`` at ``t - b``; ``num``
    pushes ``consts[a]``; the others pop their arguments and push the result.
    Regressor r is ``code[start[r]:start[r + 1]]``.
    """

    code: np.ndarray
    consts: np.ndarray
    start: np.ndarray
    depth: int


def program(exprs: list[Expr], output: str, inputs: tuple[str, ...]) -> Program:
    """The postfix code of the regressors ``exprs`` (inputs numbered in ``inputs``' order)."""
    code: list[tuple[int, int, int]] = []
    consts: list[float] = []
    start = [0]
    depth = 1

    def emit(e: Expr, level: int) -> int:
        if e.op == "num":
            consts.append(e.value)
            code.append((OPS["num"], len(consts) - 1, 0))
            return level + 1
        if e.op == "sig":
            if e.signal == output:
                code.append((OPS["y"], e.lag, 0))
            else:
                code.append((OPS["u"], inputs.index(e.signal), e.lag))
            return level + 1
        top = level
        for k, a in enumerate(e.args):
            top = max(top, emit(a, level + k))
        code.append((OPS[e.op], 0, 0))
        return top

    for e in exprs:
        depth = max(depth, emit(e, 0))
        start.append(len(code))
    return Program(np.array(code or [(0, 0, 0)], dtype=np.int64).reshape(-1, 3),
                   np.array(consts or [0.0]), np.array(start, dtype=np.int64), depth + 1)
