"""A URScript subset the simulator runs: programs other than ur_rtde's control script.

:mod:`.parser` (tokenizer and recursive-descent parser) turns a text into a syntax tree,
:mod:`.interpreter` runs it step-wise on the controller, :mod:`.builtins` holds the
functions a program may call, :mod:`.values` what those two share. The language covered:
``def``/``sec`` functions (parameters with defaults, ``return``), assignments (``global``/
``local``, list and pose elements), ``if``/``elif``/``else``, ``while``, ``break``/``continue``,
numbers, strings, ``True``/``False``, lists ``[...]``, poses ``p[...]``, indexing, calls with
keyword arguments, ``+ - * / %``, comparisons, ``and``/``or``/``not``.

Names a program calls are resolved before it runs, as the controller's compiler does: an
unknown one is ``compile_error_name_not_found:NAME:``. Blending (``r``) and the time
argument ``t`` of moves are not modelled: each move stops at its target.
"""

from fxcell.sim.urscript.builtins import BUILTINS, UNSUPPORTED
from fxcell.sim.urscript.errors import URScriptError
from fxcell.sim.urscript.interpreter import Program
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
    Token,
    Unary,
    While,
    parse,
    tokenize,
)
from fxcell.sim.urscript.values import PoseValue

__all__ = [
    "BUILTINS",
    "UNSUPPORTED",
    "Assign",
    "BinOp",
    "Call",
    "Const",
    "ExprStmt",
    "FuncDef",
    "If",
    "Index",
    "Jump",
    "ListExpr",
    "Name",
    "Node",
    "PoseValue",
    "Program",
    "Return",
    "Token",
    "URScriptError",
    "Unary",
    "While",
    "parse",
    "tokenize",
]
