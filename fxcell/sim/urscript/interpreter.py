"""The step-wise evaluator: a program as a generator the controller resumes once per cycle.

A built-in that takes time (a move, ``sleep``, ``sync``) returns what it waits for, and
:meth:`Program.step` resumes the program once that is done. Names a program calls are
resolved before it runs, as the controller's compiler does.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from fxcell.sim.motion import MotionToken
from fxcell.sim.urscript.builtins import BUILTINS, UNSUPPORTED
from fxcell.sim.urscript.errors import URScriptError
from fxcell.sim.urscript.parser import (
    Assign,
    BinOp,
    Call,
    Const,
    ExprStmt,
    FuncDef,
    If,
    Index,
    Jump,
    ListExpr,
    Name,
    Node,
    Return,
    Unary,
    While,
    parse,
)
from fxcell.sim.urscript.values import (
    Gen,
    HaltSignal,
    PoseValue,
    Wait,
    Waiting,
    as_number,
    binary_op,
    format_value,
    index_of,
)

if TYPE_CHECKING:
    from fxcell.sim.controller import Controller

MAX_STATEMENTS_PER_CYCLE = 5000  # a busy loop continues in the next cycle
SECONDARY_BUDGET = 100_000  # statements a secondary program may run (it must not take time)


class _ReturnSignal(Exception):  # noqa: N818 (control flow, not an error)
    def __init__(self, value: Any) -> None:
        self.value = value


class _JumpSignal(Exception):  # noqa: N818
    def __init__(self, kind: str) -> None:
        self.kind = kind


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
        except HaltSignal:
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
            raise URScriptError(f"cannot index {format_value(container)}")
        i = index_of(container, index)
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
                return PoseValue(as_number(v, "pose") for v in items)
            return items
        if isinstance(node, Index):
            container = yield from self._eval(node.target)
            index = yield from self._eval(node.index)
            if not isinstance(container, list | str):
                raise URScriptError(
                    f"cannot index {format_value(container)}", node.line, node.column
                )
            return container[index_of(container, index)]
        if isinstance(node, Unary):
            value = yield from self._eval(node.operand)
            if node.op == "not":
                return not value
            number = as_number(value, node.op)
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
                return binary_op(node.op, left, right)
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
        if isinstance(result, Waiting):
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
