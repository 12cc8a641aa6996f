"""The user's own module in a command line (``batch --problem``, ``profile``).

A mistake in it (a syntax error, an exception at import or in the function
called) ends the command with one line naming the module and the error;
``--debug`` lets the exception and its traceback through instead.
"""
from __future__ import annotations

import contextlib
import importlib
import os
import sys
import traceback


def describe(e: BaseException) -> str:
    """One line: the exception and where the user's code raised it."""
    if isinstance(e, SyntaxError):
        return f"SyntaxError: {e.msg} ({e.filename}, line {e.lineno})"
    frames = [f for f in traceback.extract_tb(e.__traceback__)
              if not f.filename.startswith("<frozen") and os.sep + "importlib" + os.sep not in f.filename]
    where = f" (at {frames[-1].filename}:{frames[-1].lineno})" if len(frames) > 1 else ""
    return f"{type(e).__name__}: {e}{where}"


@contextlib.contextmanager
def user_code(what: str, debug: bool):
    """Inside, an exception becomes ``SystemExit(f"{what} {describe(e)}")``, or, with ``debug``, passes."""
    try:
        yield
    except Exception as e:
        if debug:
            raise
        raise SystemExit(f"{what} {describe(e)}; --debug shows the traceback") from None


def import_user_module(module: str, what: str, debug: bool):
    """``importlib.import_module(module)`` with the working directory on ``sys.path`` (as ``python -m``
    has it), its errors as in ``user_code``."""
    if os.getcwd() not in sys.path:
        sys.path.insert(0, os.getcwd())
    with user_code(what, debug):
        return importlib.import_module(module)
