"""URScript text to a syntax tree: the tokenizer and a recursive-descent parser."""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Any

from fxcell.sim.urscript.errors import URScriptError

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
