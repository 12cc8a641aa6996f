"""Old model factory names, kept as aliases for one release: each warns and calls its replacement."""
from __future__ import annotations

import warnings


def renamed(old: str, new: str) -> None:
    """Warn that ``old`` is deprecated in favour of ``new`` (both as the caller would write them)."""
    warnings.warn(f"{old} is deprecated and will be removed in the next release: use {new}",
                  DeprecationWarning, stacklevel=3)
