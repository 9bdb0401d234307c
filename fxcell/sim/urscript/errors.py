"""The one error of a URScript program: syntax, compile or run time, with its position."""

from __future__ import annotations


class URScriptError(Exception):
    """A syntax, compile or runtime error of a program, with its script position."""

    def __init__(self, message: str, line: int = 0, column: int = 0) -> None:
        super().__init__(message)
        self.message = message
        self.line = line
        self.column = column


__all__ = ["URScriptError"]
