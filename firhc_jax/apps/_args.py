"""Argument types shared by the command-line applications: numbers with bounds
and a clear message when the value is out of them."""
from __future__ import annotations

import argparse
import math


def number(kind=float, low=None, high=None, low_open=False):
    """An argparse ``type``: ``kind`` (int or float) within ``[low, high]``
    (``(low, high]`` with ``low_open``); ``None`` leaves a side unbounded."""
    name = "an integer" if kind is int else "a number"

    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be {name}, got {text!r}") from None
        too_low = low is not None and (value <= low if low_open else value < low)
        if not math.isfinite(value) or too_low or (high is not None and value > high):
            if low is not None and high is not None and not low_open:
                bounds = f"between {low} and {high}"
            else:
                lo = "" if low is None else f"{'>' if low_open else '>='} {low}"
                bounds = " and ".join(p for p in (lo, "" if high is None else f"<= {high}") if p)
            raise argparse.ArgumentTypeError(f"must be {name} {bounds}, got {text!r}")
        return value

    return parse
