"""A URScript subset the simulator runs: programs other than ur_rtde's control script.

Tokenizer, recursive-descent parser and a step-wise evaluator. The language covered:
``def``/``sec`` functions (parameters with defaults, ``return``), assignments (``global``/
``local``, list and pose elements), ``if``/``elif``/``else``, ``while``, ``break``/``continue``,
numbers, strings, ``True``/``False``, lists ``[...]``, poses ``p[...]``, indexing, calls with
keyword arguments, ``+ - * / %``, comparisons, ``and``/``or``/``not``.

The evaluator is a generator: a builtin that takes time (a move, ``sleep``, ``sync``)
yields what it waits for, and :meth:`Program.step` resumes it once per control cycle.
Names a program calls are resolved before it runs, as the controller's compiler does: an
unknown one is ``compile_error_name_not_found:NAME:``. Blending (``r``) and the time
argument ``t`` of moves are not modelled: each move stops at its target.
"""

from __future__ import annotations

import logging
import math
import re
from collections.abc import Callable, Generator
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from fxcell.geometry import Pose
from fxcell.sim.constants import REGISTER_COUNT
from fxcell.sim.motion import JointMove, LinearMove, MotionToken

if TYPE_CHECKING:
    from fxcell.sim.controller import Controller

log = logging.getLogger(__name__)

MAX_STATEMENTS_PER_CYCLE = 5000  # a busy loop continues in the next cycle
SECONDARY_BUDGET = 100_000  # statements a secondary program may run (it must not take time)


class URScriptError(Exception):
    """A syntax, compile or runtime error of a program, with its script position."""

    def __init__(self, message: str, line: int = 0, column: int = 0) -> None:
        super().__init__(message)
        self.message = message
        self.line = line
        self.column = column


# ---------------------------------------------------------------------------- tokens

KEYWORDS = frozenset(
    {
        "def",
        "sec",
        "end",
        "if",
        "elif",
        "else",
        "while",
        "return",
        "global",
        "local",
        "True",
        "False",
        "and",
        "or",
        "not",
        "break",
        "continue",
        "thread",
    }
)
_TOKEN = re.compile(
    r"""
    (?P<ws>[ \t\r\f]+|\\\n)
  | (?P<comment>\#[^\n]*)
  | (?P<nl>\n)
  | (?P<num>(?:\d+\.\d*|\.\d+|\d+)(?:[eE][+-]?\d+)?)
  | (?P<str>"(?:[^"\\\n]|\\.)*"|'(?:[^'\\\n]|\\.)*')
  | (?P<name>[A-Za-z_][A-Za-z0-9_]*)
  | (?P<op>==|!=|<=|>=|[-+*/%<>=()\[\],:])
    """,
    re.VERBOSE,
)


@dataclass(frozen=True)
class Token:
    kind: str  # num, str, name, kw, op, nl, eof
    value: str
    line: int
    column: int


def tokenize(text: str) -> list[Token]:
    """The tokens of ``text``; newlines inside brackets are dropped. ``$ ...`` label lines
    (PolyScope's) count as comments."""
    tokens: list[Token] = []
    pos, line, line_start, depth = 0, 1, 0, 0
    while pos < len(text):
        if text[pos] == "$" and text[line_start:pos].strip() == "":
            end = text.find("\n", pos)
            pos = len(text) if end < 0 else end
            continue
        m = _TOKEN.match(text, pos)
        column = pos - line_start + 1
        if m is None:
            raise URScriptError(f"syntax_error_on_line:{line}:{text[pos]!r}", line, column)
        kind = m.lastgroup or ""
        value = m.group()
        pos = m.end()
        if kind == "nl" or (kind == "ws" and value == "\\\n"):
            if kind == "nl" and depth == 0:
                tokens.append(Token("nl", "\n", line, column))
            line += 1
            line_start = pos
            continue
        if kind in ("ws", "comment"):
            continue
        if kind == "name" and value in KEYWORDS:
            kind = "kw"
        if kind == "op" and value in "([":
            depth += 1
        elif kind == "op" and value in ")]":
            depth = max(depth - 1, 0)
        tokens.append(Token(kind, value, line, column))
    tokens.append(Token("nl", "\n", line, pos - line_start + 1))
    tokens.append(Token("eof", "", line, pos - line_start + 1))
    return tokens


# ---------------------------------------------------------------------------- syntax tree


@dataclass(frozen=True)
class Node:
    line: int = field(default=0, compare=False, kw_only=True)
    column: int = field(default=0, compare=False, kw_only=True)


@dataclass(frozen=True)
class Const(Node):
    value: Any


@dataclass(frozen=True)
class Name(Node):
    id: str


@dataclass(frozen=True)
class ListExpr(Node):
    items: tuple[Node, ...]
    pose: bool = False


@dataclass(frozen=True)
class Index(Node):
    target: Node
    index: Node


@dataclass(frozen=True)
class Call(Node):
    func: str
    args: tuple[Node, ...]
    kwargs: tuple[tuple[str, Node], ...] = ()


@dataclass(frozen=True)
class BinOp(Node):
    op: str
    left: Node
    right: Node


@dataclass(frozen=True)
class Unary(Node):
    op: str
    operand: Node


@dataclass(frozen=True)
class Assign(Node):
    target: Node
    value: Node
    scope: str = ""  # "", "global" or "local"


@dataclass(frozen=True)
class ExprStmt(Node):
    expr: Node


@dataclass(frozen=True)
class If(Node):
    branches: tuple[tuple[Node, tuple[Node, ...]], ...]
    orelse: tuple[Node, ...] = ()


@dataclass(frozen=True)
class While(Node):
    cond: Node
    body: tuple[Node, ...]


@dataclass(frozen=True)
class Return(Node):
    value: Node | None


@dataclass(frozen=True)
class Jump(Node):
    kind: str  # break | continue


@dataclass(frozen=True)
class FuncDef(Node):
    name: str
    params: tuple[tuple[str, Node | None], ...]
    body: tuple[Node, ...]
    secondary: bool = False


_BINARY_LEVELS: tuple[tuple[str, ...], ...] = (
    ("or",),
    ("and",),
    ("==", "!=", "<", "<=", ">", ">="),
    ("+", "-"),
    ("*", "/", "%"),
)


class Parser:
    """Recursive descent over :func:`tokenize`'s tokens."""

    def __init__(self, text: str) -> None:
        self.tokens = tokenize(text)
        self.pos = 0

    # -- helpers
    @property
    def tok(self) -> Token:
        return self.tokens[self.pos]

    def _error(self, what: str, tok: Token | None = None) -> URScriptError:
        t = tok or self.tok
        found = t.value if t.kind not in ("nl", "eof") else "end of line"
        return URScriptError(
            f"syntax_error_on_line:{t.line}:{what}, found {found!r}", t.line, t.column
        )

    def _at(self, kind: str, value: str | None = None) -> bool:
        t = self.tok
        return t.kind == kind and (value is None or t.value == value)

    def _take(self, kind: str, value: str | None = None) -> Token:
        if not self._at(kind, value):
            raise self._error(f"expected {value or kind}")
        t = self.tok
        self.pos += 1
        return t

    def _skip_newlines(self) -> None:
        while self._at("nl"):
            self.pos += 1

    # -- statements
    def program(self) -> tuple[Node, ...]:
        body = self._block(top=True)
        if not self._at("eof"):
            raise self._error("unexpected")
        return body

    def _block(self, top: bool = False, ends: tuple[str, ...] = ("end",)) -> tuple[Node, ...]:
        out: list[Node] = []
        while True:
            self._skip_newlines()
            t = self.tok
            if t.kind == "eof":
                if not top:
                    raise self._error("expected end")
                return tuple(out)
            if t.kind == "kw" and t.value in ends and not top:
                return tuple(out)
            out.append(self._statement())

    def _end_of_statement(self) -> None:
        if not self._at("eof"):
            self._take("nl")

    def _statement(self) -> Node:
        t = self.tok
        ln, col = t.line, t.column
        if t.kind == "kw":
            if t.value in ("def", "sec"):
                return self._funcdef()
            if t.value == "if":
                return self._if()
            if t.value == "while":
                self.pos += 1
                cond = self.expression()
                self._take("op", ":")
                body = self._block()
                self._take("kw", "end")
                self._end_of_statement()
                return While(cond, body, line=ln, column=col)
            if t.value == "return":
                self.pos += 1
                value = None if self._at("nl") or self._at("eof") else self.expression()
                self._end_of_statement()
                return Return(value, line=ln, column=col)
            if t.value in ("break", "continue"):
                self.pos += 1
                self._end_of_statement()
                return Jump(t.value, line=ln, column=col)
            if t.value in ("global", "local"):
                self.pos += 1
                target = Name(self._take("name").value, line=ln, column=col)
                self._take("op", "=")
                value = self.expression()
                self._end_of_statement()
                return Assign(target, value, t.value, line=ln, column=col)
            if t.value == "thread":
                raise URScriptError("thread is not supported by the simulator", t.line, t.column)
            if t.value not in ("True", "False", "not"):  # those start an expression
                raise self._error("unexpected keyword")
        expr = self.expression()
        if self._at("op", "="):
            if not isinstance(expr, Name | Index):
                raise self._error("cannot assign to this")
            self.pos += 1
            value = self.expression()
            self._end_of_statement()
            return Assign(expr, value, line=ln, column=col)
        self._end_of_statement()
        return ExprStmt(expr, line=ln, column=col)

    def _funcdef(self) -> FuncDef:
        t = self._take("kw")
        name = self._take("name").value
        self._take("op", "(")
        params: list[tuple[str, Node | None]] = []
        while not self._at("op", ")"):
            pname = self._take("name").value
            default = None
            if self._at("op", "="):
                self.pos += 1
                default = self.expression()
            params.append((pname, default))
            if not self._at("op", ")"):
                self._take("op", ",")
        self._take("op", ")")
        self._take("op", ":")
        body = self._block()
        self._take("kw", "end")
        self._end_of_statement()
        return FuncDef(name, tuple(params), body, t.value == "sec", line=t.line, column=t.column)

    def _if(self) -> If:
        t = self._take("kw", "if")
        branches: list[tuple[Node, tuple[Node, ...]]] = []
        cond = self.expression()
        self._take("op", ":")
        body = self._block(ends=("elif", "else", "end"))
        branches.append((cond, body))
        orelse: tuple[Node, ...] = ()
        while True:
            if self._at("kw", "elif"):
                self.pos += 1
                cond = self.expression()
                self._take("op", ":")
                branches.append((cond, self._block(ends=("elif", "else", "end"))))
                continue
            if self._at("kw", "else"):
                self.pos += 1
                self._take("op", ":")
                orelse = self._block()
            self._take("kw", "end")
            break
        self._end_of_statement()
        return If(tuple(branches), orelse, line=t.line, column=t.column)

    # -- expressions
    def expression(self, level: int = 0) -> Node:
        if level == len(_BINARY_LEVELS):
            return self._unary()
        if level == 2 and self._at("kw", "not"):  # "not" binds looser than comparisons
            t = self.tok
            self.pos += 1
            return Unary("not", self.expression(2), line=t.line, column=t.column)
        left = self.expression(level + 1)
        ops = _BINARY_LEVELS[level]
        while (self.tok.kind in ("op", "kw")) and self.tok.value in ops:
            t = self.tok
            self.pos += 1
            right = self.expression(level + 1)
            left = BinOp(t.value, left, right, line=t.line, column=t.column)
        return left

    def _unary(self) -> Node:
        t = self.tok
        if t.kind == "op" and t.value in ("-", "+"):
            self.pos += 1
            return Unary(t.value, self._unary(), line=t.line, column=t.column)
        return self._postfix(self._atom())

    def _postfix(self, node: Node) -> Node:
        while self._at("op", "["):
            t = self.tok
            self.pos += 1
            index = self.expression()
            self._take("op", "]")
            node = Index(node, index, line=t.line, column=t.column)
        return node

    def _atom(self) -> Node:
        t = self.tok
        ln, col = t.line, t.column
        if t.kind == "num":
            self.pos += 1
            text = t.value
            is_float = any(c in text for c in ".eE")
            return Const(float(text) if is_float else int(text), line=ln, column=col)
        if t.kind == "str":
            self.pos += 1
            return Const(_unescape(t.value[1:-1]), line=ln, column=col)
        if t.kind == "kw" and t.value in ("True", "False"):
            self.pos += 1
            return Const(t.value == "True", line=ln, column=col)
        if t.kind == "op" and t.value == "(":
            self.pos += 1
            inner = self.expression()
            self._take("op", ")")
            return inner
        if t.kind == "op" and t.value == "[":
            return ListExpr(self._items(), line=ln, column=col)
        if t.kind == "name":
            self.pos += 1
            if t.value == "p" and self._at("op", "["):
                return ListExpr(self._items(), pose=True, line=ln, column=col)
            if self._at("op", "("):
                return self._call(t.value, ln, col)
            return Name(t.value, line=ln, column=col)
        raise self._error("expected an expression")

    def _items(self) -> tuple[Node, ...]:
        self._take("op", "[")
        items: list[Node] = []
        while not self._at("op", "]"):
            items.append(self.expression())
            if not self._at("op", "]"):
                self._take("op", ",")
        self._take("op", "]")
        return tuple(items)

    def _call(self, func: str, ln: int, col: int) -> Call:
        self._take("op", "(")
        args: list[Node] = []
        kwargs: list[tuple[str, Node]] = []
        while not self._at("op", ")"):
            if self._at("name") and self.tokens[self.pos + 1].value == "=":
                key = self._take("name").value
                self.pos += 1
                kwargs.append((key, self.expression()))
            else:
                if kwargs:
                    raise self._error("positional argument after a keyword argument")
                args.append(self.expression())
            if not self._at("op", ")"):
                self._take("op", ",")
        self._take("op", ")")
        return Call(func, tuple(args), tuple(kwargs), line=ln, column=col)


def _unescape(text: str) -> str:
    return re.sub(r"\\(.)", lambda m: {"n": "\n", "t": "\t"}.get(m.group(1), m.group(1)), text)


def parse(text: str) -> tuple[Node, ...]:
    """The statements of a program text (URScriptError on a syntax error)."""
    return Parser(text).program()


# ---------------------------------------------------------------------------- values


class PoseValue(list[float]):
    """A ``p[...]`` value: a list that remembers it is a pose."""


def _fmt(value: object) -> str:
    if isinstance(value, bool):
        return "True" if value else "False"
    if isinstance(value, PoseValue):
        return "p[" + ", ".join(_fmt(v) for v in value) + "]"
    if isinstance(value, list):
        return "[" + ", ".join(_fmt(v) for v in value) + "]"
    if isinstance(value, float):
        return f"{value:.6g}"
    return str(value)


def _number(value: object, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise URScriptError(f"{what}: expected a number, got {_fmt(value)}")
    return float(value)


def _six(value: object, what: str) -> list[float]:
    if not isinstance(value, list) or len(value) != 6:
        raise URScriptError(f"{what}: expected 6 values, got {_fmt(value)}")
    return [_number(v, what) for v in value]


def _binary(op: str, a: Any, b: Any) -> Any:
    if op == "and":
        return bool(a) and bool(b)
    if op == "or":
        return bool(a) or bool(b)
    if op == "==":
        return bool(a == b)
    if op == "!=":
        return bool(a != b)
    if isinstance(a, list) and isinstance(b, list) and op in "+-":
        if len(a) != len(b):
            raise URScriptError(f"'{op}' on lists of different lengths")
        out = [_binary(op, x, y) for x, y in zip(a, b, strict=True)]
        return PoseValue(out) if isinstance(a, PoseValue) or isinstance(b, PoseValue) else out
    if op == "+" and isinstance(a, str) and isinstance(b, str):
        return a + b
    x, y = _number(a, op), _number(b, op)
    both_int = isinstance(a, int) and isinstance(b, int)
    if op in ("<", "<=", ">", ">="):
        return {"<": x < y, "<=": x <= y, ">": x > y, ">=": x >= y}[op]
    if op in ("/", "%") and y == 0:
        raise URScriptError("division by zero")
    if both_int:
        ia, ib = int(a), int(b)
        if op == "/":
            q = abs(ia) // abs(ib)  # integer division truncates toward zero
            return q if (ia >= 0) == (ib >= 0) else -q
        if op == "%":
            return int(math.fmod(ia, ib))
        return {"+": ia + ib, "-": ia - ib, "*": ia * ib}[op]
    if op == "%":
        return math.fmod(x, y)
    return {"+": x + y, "-": x - y, "*": x * y, "/": x / y}[op]


# ---------------------------------------------------------------------------- evaluation


class _ReturnSignal(Exception):  # noqa: N818 (control flow, not an error)
    def __init__(self, value: Any) -> None:
        self.value = value


class _JumpSignal(Exception):  # noqa: N818
    def __init__(self, kind: str) -> None:
        self.kind = kind


class _HaltSignal(Exception):  # noqa: N818
    pass


Wait = MotionToken | float | None  # a motion, a controller time, or the next cycle
Gen = Generator[Wait, None, Any]
Builtin = Callable[["Program", list[Any], dict[str, Any]], Any]


def _signature(
    *names: str, **defaults: Any
) -> Callable[[list[Any], dict[str, Any], str], list[Any]]:
    """Bind positional and keyword arguments to ``names`` (defaults from ``defaults``)."""

    def bind(args: list[Any], kwargs: dict[str, Any], func: str) -> list[Any]:
        if len(args) > len(names):
            raise URScriptError(f"{func}: too many arguments")
        values = dict(zip(names, args, strict=False))
        for key, value in kwargs.items():
            if key not in names or key in values:
                raise URScriptError(f"{func}: unexpected argument {key}")
            values[key] = value
        out = []
        for n in names:
            if n in values:
                out.append(values[n])
            elif n in defaults:
                out.append(defaults[n])
            else:
                raise URScriptError(f"{func}: missing argument {n}")
        return out

    return bind


class Program:
    """One running URScript program (main or secondary) on the simulated controller."""

    def __init__(self, controller: Controller, text: str, *, secondary: bool = False) -> None:
        self.c = controller
        self.secondary = secondary
        body = parse(text)
        self.functions: dict[str, FuncDef] = {}
        top: list[Node] = []
        for stmt in body:
            if isinstance(stmt, FuncDef):
                self.functions[stmt.name] = stmt
            else:
                top.append(stmt)
        defs = [s for s in body if isinstance(s, FuncDef)]
        self.body: tuple[Node, ...]
        if not top and len(defs) == 1:  # "def main(): ... end": the program runs main
            d = defs[0]
            self.name = d.name
            self.body = (ExprStmt(Call(d.name, (), line=d.line, column=d.column), line=d.line),)
        else:
            self.name = "script"
            self.body = tuple(top)
        self._collect(body)
        self._check_names(body)
        self.globals: dict[str, Any] = {}
        self.frames: list[dict[str, Any]] = []
        self.finished = False
        self.error: URScriptError | None = None
        self._wait: Wait = None
        self._waiting = False
        self._budget = 0
        self._position = (0, 0)
        self._gen: Gen = self._run()

    # -- static checks
    def _collect(self, nodes: tuple[Node, ...]) -> None:
        for node in nodes:
            if isinstance(node, FuncDef):
                self.functions.setdefault(node.name, node)
                self._collect(node.body)
            elif isinstance(node, If):
                for _, body in node.branches:
                    self._collect(body)
                self._collect(node.orelse)
            elif isinstance(node, While):
                self._collect(node.body)

    def _check_names(self, nodes: tuple[Node, ...]) -> None:
        """Every called function exists (the controller's compile step)."""
        stack: list[Any] = list(nodes)
        while stack:
            node = stack.pop()
            if isinstance(node, tuple):
                stack.extend(node)
                continue
            if not isinstance(node, Node):
                continue
            if isinstance(node, Call) and node.func not in self.functions:
                if node.func in UNSUPPORTED:
                    raise URScriptError(
                        f"{node.func} is not supported by the simulator", node.line, node.column
                    )
                if node.func not in BUILTINS:
                    raise URScriptError(
                        f"compile_error_name_not_found:{node.func}:", node.line, node.column
                    )
            for value in vars(node).values():
                if isinstance(value, Node | tuple):
                    stack.append(value)

    # -- running
    def step(self) -> bool:
        """Run until the program waits or ends; True once it has ended (see ``error``)."""
        if self.finished:
            return True
        if self._waiting and not self._ready(self._wait):
            return False
        self._budget = SECONDARY_BUDGET if self.secondary else MAX_STATEMENTS_PER_CYCLE
        try:
            self._wait = next(self._gen)
            self._waiting = True
            if self.secondary:
                raise URScriptError("a secondary program cannot take time (move, sleep, sync)")
            return False
        except StopIteration:
            self.finished = True
        except URScriptError as exc:
            if not exc.line:
                exc.line, exc.column = self._position
            self.error = exc
            self.finished = True
        return True

    def terminate(self) -> None:
        self.finished = True
        self._gen.close()

    def _ready(self, wait: Wait) -> bool:
        if wait is None:
            return True
        if isinstance(wait, MotionToken):
            return wait.done
        return self.c.time >= wait - 1e-9

    def _run(self) -> Gen:
        try:
            yield from self._block(self.body)
        except _HaltSignal:
            return
        except _ReturnSignal:
            return
        except _JumpSignal as exc:
            raise URScriptError(f"{exc.kind} outside a loop") from None

    def _block(self, body: tuple[Node, ...]) -> Gen:
        for stmt in body:
            self._position = (stmt.line, stmt.column)
            self._budget -= 1
            if self._budget <= 0:
                if self.secondary:
                    raise URScriptError("secondary program runs too long")
                yield None  # continue in the next cycle
                self._budget = MAX_STATEMENTS_PER_CYCLE
            yield from self._statement(stmt)

    def _statement(self, stmt: Node) -> Gen:
        if isinstance(stmt, ExprStmt):
            yield from self._eval(stmt.expr)
        elif isinstance(stmt, Assign):
            value = yield from self._eval(stmt.value)
            yield from self._assign(stmt, value)
        elif isinstance(stmt, If):
            for cond, body in stmt.branches:
                if (yield from self._eval(cond)):
                    yield from self._block(body)
                    return
            yield from self._block(stmt.orelse)
        elif isinstance(stmt, While):
            while (yield from self._eval(stmt.cond)):
                try:
                    yield from self._block(stmt.body)
                except _JumpSignal as jump:
                    if jump.kind == "break":
                        break
        elif isinstance(stmt, Return):
            value = None if stmt.value is None else (yield from self._eval(stmt.value))
            raise _ReturnSignal(value)
        elif isinstance(stmt, Jump):
            raise _JumpSignal(stmt.kind)
        elif isinstance(stmt, FuncDef):
            self.functions[stmt.name] = stmt

    def _assign(self, stmt: Assign, value: Any) -> Gen:
        target = stmt.target
        if isinstance(target, Name):
            scope = self._scope_for(target.id, stmt.scope)
            scope[target.id] = value
            return
        assert isinstance(target, Index)
        container = yield from self._eval(target.target)
        index = yield from self._eval(target.index)
        self._set_item(container, index, value)

    def _scope_for(self, name: str, declared: str) -> dict[str, Any]:
        if not self.frames or declared == "global":
            return self.globals
        frame = self.frames[-1]
        if declared == "local" or name in frame or name not in self.globals:
            return frame
        return self.globals

    @staticmethod
    def _set_item(container: Any, index: Any, value: Any) -> None:
        if not isinstance(container, list):
            raise URScriptError(f"cannot index {_fmt(container)}")
        i = _index(container, index)
        container[i] = value

    def _lookup(self, node: Name) -> Any:
        if self.frames and node.id in self.frames[-1]:
            return self.frames[-1][node.id]
        if node.id in self.globals:
            return self.globals[node.id]
        raise URScriptError(f"name '{node.id}' is not defined", node.line, node.column)

    def _eval(self, node: Node) -> Gen:
        if isinstance(node, Const):
            return node.value
        if isinstance(node, Name):
            return self._lookup(node)
        if isinstance(node, ListExpr):
            items = []
            for item in node.items:
                items.append((yield from self._eval(item)))
            if node.pose:
                if len(items) != 6:
                    raise URScriptError("a pose has 6 values", node.line, node.column)
                return PoseValue(_number(v, "pose") for v in items)
            return items
        if isinstance(node, Index):
            container = yield from self._eval(node.target)
            index = yield from self._eval(node.index)
            if not isinstance(container, list | str):
                raise URScriptError(f"cannot index {_fmt(container)}", node.line, node.column)
            return container[_index(container, index)]
        if isinstance(node, Unary):
            value = yield from self._eval(node.operand)
            if node.op == "not":
                return not value
            number = _number(value, node.op)
            if node.op == "-":
                return -value if isinstance(value, int) else -number
            return value
        if isinstance(node, BinOp):
            left = yield from self._eval(node.left)
            if node.op == "and" and not left:
                return False
            if node.op == "or" and left:
                return True
            right = yield from self._eval(node.right)
            try:
                return _binary(node.op, left, right)
            except URScriptError as exc:
                raise URScriptError(exc.message, node.line, node.column) from None
        if isinstance(node, Call):
            return (yield from self._call(node))
        raise URScriptError(f"cannot evaluate {type(node).__name__}", node.line, node.column)

    def _call(self, node: Call) -> Gen:
        args = []
        for a in node.args:
            args.append((yield from self._eval(a)))
        kwargs = {}
        for key, a in node.kwargs:
            kwargs[key] = yield from self._eval(a)
        self._position = (node.line, node.column)
        func = self.functions.get(node.func)
        if func is not None:
            return (yield from self._user_call(func, args, kwargs))
        builtin = BUILTINS[node.func]
        try:
            result = builtin(self, args, kwargs)
        except URScriptError as exc:
            raise URScriptError(
                exc.message, exc.line or node.line, exc.column or node.column
            ) from None
        if isinstance(result, _Waiting):
            yield result.wait
            if isinstance(result.wait, MotionToken):
                failed = result.wait.failed
                if failed is not None and failed not in ("stopped", "safety stop"):
                    raise URScriptError(f"{node.func}: {failed}", node.line, node.column)
            return None
        return result

    def _user_call(self, func: FuncDef, args: list[Any], kwargs: dict[str, Any]) -> Gen:
        names = [n for n, _ in func.params]
        if len(args) > len(names):
            raise URScriptError(f"{func.name}: too many arguments")
        frame: dict[str, Any] = dict(zip(names, args, strict=False))
        for key, value in kwargs.items():
            if key not in names:
                raise URScriptError(f"{func.name}: unexpected argument {key}")
            frame[key] = value
        for n, default in func.params:
            if n not in frame:
                if default is None:
                    raise URScriptError(f"{func.name}: missing argument {n}")
                frame[n] = yield from self._eval(default)
        if len(self.frames) > 100:
            raise URScriptError("recursion too deep")
        self.frames.append(frame)
        try:
            yield from self._block(func.body)
        except _ReturnSignal as ret:
            return ret.value
        finally:
            self.frames.pop()
        return None


def _index(container: list[Any] | str, index: Any) -> int:
    if isinstance(index, bool) or not isinstance(index, int):
        raise URScriptError(f"index must be an integer, got {_fmt(index)}")
    if not 0 <= index < len(container):
        raise URScriptError(f"index {index} out of range (length {len(container)})")
    return index


# ---------------------------------------------------------------------------- builtins


@dataclass
class _Waiting:
    wait: Wait


BUILTINS: dict[str, Builtin] = {}
UNSUPPORTED = frozenset(
    {
        "force_mode",
        "end_force_mode",
        "force_mode_set_damping",
        "force_mode_set_gain_scaling",
        "freedrive_mode",
        "end_freedrive_mode",
        "teach_mode",
        "end_teach_mode",
        "movec",
        "servoj",
        "servoc",
        "speedj",
        "speedl",
        "socket_open",
        "socket_send_string",
        "socket_read_ascii_float",
        "run",
        "join",
        "kill",
        "enter_critical",
        "exit_critical",
    }
)


def builtin(name: str, *names: str, **defaults: Any) -> Callable[[Callable[..., Any]], Any]:
    bind = _signature(*names, **defaults)

    def register(fn: Callable[..., Any]) -> Callable[..., Any]:
        def call(program: Program, args: list[Any], kwargs: dict[str, Any]) -> Any:
            return fn(program, *bind(args, kwargs, name))

        BUILTINS[name] = call
        return fn

    return register


def _joints_or_ik(program: Program, target: Any, what: str) -> np.ndarray:
    arm = program.c.arm
    values = _six(target, what)
    if isinstance(target, PoseValue):
        try:
            return np.asarray(arm.kinematics.inverse(Pose.from_ur(values), arm.q), dtype=float)
        except Exception as exc:
            raise URScriptError(f"{what}: no inverse kinematics solution ({exc})") from None
    if any(abs(v) > 2 * math.pi + 1e-9 for v in values):
        raise URScriptError(f"{what}: joint positions {_fmt(values)} outside ±2π")
    return np.asarray(values, dtype=float)


def _check_move(program: Program, what: str, a: Any, v: Any) -> tuple[float, float]:
    if program.secondary:
        raise URScriptError(f"{what}: a secondary program cannot move the arm")
    a_, v_ = _number(a, what), _number(v, what)
    if not (a_ > 0 and v_ > 0 and math.isfinite(a_) and math.isfinite(v_)):
        raise URScriptError(f"{what}: invalid speed {v_} or acceleration {a_}")
    if not program.c.can_move:
        raise URScriptError(f"{what}: the robot cannot move (not running or stopped)")
    return a_, v_


@builtin("movej", "q", "a", "v", "t", "r", a=1.4, v=1.05, t=0.0, r=0.0)
def _movej(p: Program, q: Any, a: Any, v: Any, t: Any, r: Any) -> _Waiting:
    acc, vel = _check_move(p, "movej", a, v)
    target = _joints_or_ik(p, q, "movej")
    arm = p.c.arm
    return _Waiting(arm.run(JointMove(arm, target, vel, acc)))


def _linear(p: Program, what: str, pose: Any, a: Any, v: Any) -> _Waiting:
    acc, vel = _check_move(p, what, a, v)
    arm = p.c.arm
    final_q = None
    if isinstance(pose, PoseValue):
        target = Pose.from_ur(_six(pose, what))
    else:
        final_q = _joints_or_ik(p, pose, what)
        target = arm.kinematics.forward(final_q)
    return _Waiting(arm.run(LinearMove(arm, target, vel, acc, final_q=final_q)))


@builtin("movel", "pose", "a", "v", "t", "r", a=1.2, v=0.25, t=0.0, r=0.0)
def _movel(p: Program, pose: Any, a: Any, v: Any, t: Any, r: Any) -> _Waiting:
    return _linear(p, "movel", pose, a, v)


@builtin("movep", "pose", "a", "v", "r", a=1.2, v=0.25, r=0.0)
def _movep(p: Program, pose: Any, a: Any, v: Any, r: Any) -> _Waiting:
    return _linear(p, "movep", pose, a, v)


def _stop(p: Program, what: str, a: Any) -> _Waiting:
    if p.secondary:
        raise URScriptError(f"{what}: a secondary program cannot move the arm")
    decel = _number(a, what)
    if not decel > 0:
        raise URScriptError(f"{what}: deceleration must be > 0")
    return _Waiting(p.c.arm.stop_motion(decel))


@builtin("stopj", "a")
def _stopj(p: Program, a: Any) -> _Waiting:
    return _stop(p, "stopj", a)


@builtin("stopl", "a", "aRot", aRot=None)
def _stopl(p: Program, a: Any, a_rot: Any) -> _Waiting:
    return _stop(p, "stopl", a)


@builtin("sleep", "t")
def _sleep(p: Program, t: Any) -> _Waiting:
    seconds = _number(t, "sleep")
    if seconds < 0:
        raise URScriptError("sleep: negative time")
    return _Waiting(p.c.time + seconds)


@builtin("sync")
def _sync(p: Program) -> _Waiting:
    return _Waiting(None)


@builtin("halt")
def _halt(p: Program) -> None:
    raise _HaltSignal()


@builtin("textmsg", "s1", "s2", s2="")
def _textmsg(p: Program, s1: Any, s2: Any) -> None:
    p.c.text_message(_fmt(s1) + _fmt(s2))


@builtin("popup", "s", "title", "warning", "error", "blocking", title="Popup", warning=False,
         error=False, blocking=False)  # fmt: skip
def _popup(p: Program, s: Any, title: Any, warning: Any, error: Any, blocking: Any) -> None:
    p.c.text_message(f"popup {_fmt(title)}: {_fmt(s)}")


def _digital(p: Program, what: str, n: Any, b: Any, count: int, shift: int) -> None:
    if isinstance(n, bool) or not isinstance(n, int) or not 0 <= n < count:
        raise URScriptError(f"{what}: output {_fmt(n)} out of range 0..{count - 1}")
    p.c.set_digital_output(shift + n, bool(b))


@builtin("set_standard_digital_out", "n", "b")
def _set_standard(p: Program, n: Any, b: Any) -> None:
    _digital(p, "set_standard_digital_out", n, b, 8, 0)


BUILTINS["set_digital_out"] = BUILTINS["set_standard_digital_out"]


@builtin("set_configurable_digital_out", "n", "b")
def _set_configurable(p: Program, n: Any, b: Any) -> None:
    _digital(p, "set_configurable_digital_out", n, b, 8, 8)


@builtin("set_tool_digital_out", "n", "b")
def _set_tool(p: Program, n: Any, b: Any) -> None:
    _digital(p, "set_tool_digital_out", n, b, 2, 16)


def _bit(word: int, n: Any, count: int, what: str) -> bool:
    if isinstance(n, bool) or not isinstance(n, int) or not 0 <= n < count:
        raise URScriptError(f"{what}: {_fmt(n)} out of range 0..{count - 1}")
    return bool((word >> n) & 1)


@builtin("get_standard_digital_out", "n")
def _get_standard_out(p: Program, n: Any) -> bool:
    return _bit(p.c.io.output_bits, n, 8, "get_standard_digital_out")


@builtin("get_configurable_digital_out", "n")
def _get_configurable_out(p: Program, n: Any) -> bool:
    return _bit(p.c.io.output_bits >> 8, n, 8, "get_configurable_digital_out")


@builtin("get_standard_digital_in", "n")
def _get_standard_in(p: Program, n: Any) -> bool:
    return _bit(p.c.digital_input_bits, n, 8, "get_standard_digital_in")


BUILTINS["get_digital_in"] = BUILTINS["get_standard_digital_in"]
BUILTINS["get_digital_out"] = BUILTINS["get_standard_digital_out"]


@builtin("set_tcp", "pose")
def _set_tcp(p: Program, pose: Any) -> None:
    tcp = _six(pose, "set_tcp")
    p.c.arm.set_tcp(tcp)
    p.c.tcp = tuple(tcp)


@builtin("set_payload", "m", "cog", cog=None)
def _set_payload(p: Program, m: Any, cog: Any) -> None:
    mass = _number(m, "set_payload")
    if mass < 0:
        raise URScriptError("set_payload: negative mass")
    centre = None if cog is None else tuple(_number(v, "set_payload") for v in cog)
    if centre is not None and len(centre) != 3:
        raise URScriptError("set_payload: cog must have 3 values")
    p.c.set_payload(mass, centre)


@builtin("set_target_payload", "m", "cog", "inertia", inertia=None)
def _set_target_payload(p: Program, m: Any, cog: Any, inertia: Any) -> None:
    _set_payload(p, m, cog)


@builtin("set_payload_mass", "m")
def _set_payload_mass(p: Program, m: Any) -> None:
    _set_payload(p, m, None)


@builtin("set_payload_cog", "CoG")
def _set_payload_cog(p: Program, cog: Any) -> None:
    _set_payload(p, p.c.payload_mass, cog)


@builtin("get_actual_joint_positions")
def _get_q(p: Program) -> list[float]:
    return [float(v) for v in p.c.arm.q]


BUILTINS["get_target_joint_positions"] = BUILTINS["get_actual_joint_positions"]


@builtin("get_actual_joint_speeds")
def _get_qd(p: Program) -> list[float]:
    return [float(v) for v in p.c.arm.qd]


@builtin("get_actual_tcp_pose")
def _get_tcp(p: Program) -> PoseValue:
    return PoseValue(p.c.arm.tcp_pose().as_ur())


BUILTINS["get_target_tcp_pose"] = BUILTINS["get_actual_tcp_pose"]


@builtin("get_forward_kin", "q", "tcp", q=None, tcp=None)
def _fk(p: Program, q: Any, tcp: Any) -> PoseValue:
    arm = p.c.arm
    joints = arm.q if q is None else np.asarray(_six(q, "get_forward_kin"))
    kin = arm.kinematics
    if tcp is not None and arm.make_kinematics is not None:
        kin = arm.make_kinematics(tuple(_six(tcp, "get_forward_kin")))
    return PoseValue(kin.forward(joints).as_ur())


@builtin("get_inverse_kin", "x", "qnear", "maxPositionError", "maxOrientationError", "tcp",
         qnear=None, maxPositionError=1e-10, maxOrientationError=1e-10, tcp=None)  # fmt: skip
def _ik(p: Program, x: Any, qnear: Any, _pe: Any, _oe: Any, tcp: Any) -> list[float]:
    arm = p.c.arm
    seed = arm.q if qnear is None else np.asarray(_six(qnear, "get_inverse_kin"))
    try:
        q = arm.kinematics.inverse(Pose.from_ur(_six(x, "get_inverse_kin")), seed)
    except Exception as exc:
        raise URScriptError(f"get_inverse_kin: no solution ({exc})") from None
    return [float(v) for v in q]


@builtin("pose_trans", "p_from", "p_from_to")
def _pose_trans(p: Program, a: Any, b: Any) -> PoseValue:
    result = Pose.from_ur(_six(a, "pose_trans")) @ Pose.from_ur(_six(b, "pose_trans"))
    return PoseValue(result.as_ur())


@builtin("pose_inv", "p_from")
def _pose_inv(p: Program, a: Any) -> PoseValue:
    return PoseValue(Pose.from_ur(_six(a, "pose_inv")).inverse().as_ur())


@builtin("is_steady")
def _is_steady(p: Program) -> bool:
    return not p.c.arm.moving


def _register(p: Program, what: str, address: Any) -> int:
    if isinstance(address, bool) or not isinstance(address, int):
        raise URScriptError(f"{what}: address must be an integer")
    if not 0 <= address < REGISTER_COUNT:
        raise URScriptError(f"{what}: address {address} out of range 0..{REGISTER_COUNT - 1}")
    return address


@builtin("write_output_integer_register", "address", "value")
def _write_int(p: Program, address: Any, value: Any) -> None:
    i = _register(p, "write_output_integer_register", address)
    p.c.registers.out_int[i] = int(_number(value, "write_output_integer_register"))


@builtin("write_output_float_register", "address", "value")
def _write_float(p: Program, address: Any, value: Any) -> None:
    i = _register(p, "write_output_float_register", address)
    p.c.registers.out_double[i] = _number(value, "write_output_float_register")


@builtin("write_output_boolean_register", "address", "value")
def _write_bool(p: Program, address: Any, value: Any) -> None:
    _bit(0, address, 64, "write_output_boolean_register")  # range check
    n = int(address)
    regs = p.c.registers
    regs.out_bits_high = (regs.out_bits_high & ~(1 << n)) | (int(bool(value)) << n)


@builtin("read_input_integer_register", "address")
def _read_int(p: Program, address: Any) -> int:
    return p.c.registers.in_int[_register(p, "read_input_integer_register", address)]


@builtin("read_input_float_register", "address")
def _read_float(p: Program, address: Any) -> float:
    return p.c.registers.in_double[_register(p, "read_input_float_register", address)]


@builtin("read_input_boolean_register", "address")
def _read_bool(p: Program, address: Any) -> bool:
    return _bit(p.c.registers.in_bits_high, address, 64, "read_input_boolean_register")


@builtin("rtde_set_watchdog", "variable_name", "min_frequency", "action", action="pause")
def _rtde_set_watchdog(p: Program, variable_name: Any, min_frequency: Any, action: Any) -> None:
    what = "rtde_set_watchdog"
    if not isinstance(variable_name, str) or not variable_name.startswith("input_"):
        raise URScriptError(f"{what}: {variable_name!r} is not an RTDE input variable")
    frequency = _number(min_frequency, what)
    if not (math.isfinite(frequency) and frequency >= 0):
        raise URScriptError(f"{what}: invalid frequency {frequency}")
    kind = str(action).lower()
    if kind not in ("ignore", "pause", "stop"):
        raise URScriptError(f'{what}: action must be "ignore", "pause" or "stop"')
    if frequency == 0 or kind == "ignore":
        p.c.watchdog = None  # a zero frequency turns the watchdog off
        return
    p.c.set_watchdog(variable_name, frequency, action=kind)


@builtin("to_str", "val")
def _to_str(p: Program, val: Any) -> str:
    return _fmt(val)


@builtin("str_cat", "op1", "op2")
def _str_cat(p: Program, a: Any, b: Any) -> str:
    return _fmt(a) + _fmt(b)


@builtin("length", "v")
def _length(p: Program, v: Any) -> int:
    if not isinstance(v, list | str):
        raise URScriptError("length: expected a list or a string")
    return len(v)


def _math(name: str, fn: Callable[..., float], *names: str) -> None:
    @builtin(name, *names)
    def call(p: Program, *args: Any) -> float:
        try:
            return float(fn(*(_number(a, name) for a in args)))
        except (ValueError, OverflowError):
            raise URScriptError(f"{name}: argument out of domain") from None


for _name, _fn, _args in (
    ("sqrt", math.sqrt, ("f",)),
    ("sin", math.sin, ("f",)),
    ("cos", math.cos, ("f",)),
    ("tan", math.tan, ("f",)),
    ("asin", math.asin, ("f",)),
    ("acos", math.acos, ("f",)),
    ("atan", math.atan, ("f",)),
    ("atan2", math.atan2, ("x", "y")),
    ("pow", math.pow, ("base", "exponent")),
    ("log", lambda b, f: math.log(f, b), ("b", "f")),
    ("d2r", math.radians, ("d",)),
    ("r2d", math.degrees, ("r",)),
    ("fabs", math.fabs, ("f",)),
):
    _math(_name, _fn, *_args)


@builtin("floor", "f")
def _floor(p: Program, f: Any) -> int:
    return math.floor(_number(f, "floor"))


@builtin("ceil", "f")
def _ceil(p: Program, f: Any) -> int:
    return math.ceil(_number(f, "ceil"))


@builtin("norm", "a")
def _norm(p: Program, a: Any) -> float:
    if isinstance(a, list):
        return math.sqrt(sum(_number(v, "norm") ** 2 for v in a))
    return abs(_number(a, "norm"))
