"""Argparse types of the ``pipps`` command line: each option's text is read and checked at parse time.

A bad value is refused by argparse itself, in one line that names the option
(``pipps plot: error: argument --size: expected WIDTHxHEIGHT …``), before any file is read or any
program compiled. What cannot be judged from the text alone (a cost's name for the task, a noise
multiplier against the task's noise, memory against the machine) is checked before any work by
:mod:`pipps.experiments.preflight` and the configuration's own validation.
"""

from __future__ import annotations

import argparse
import math


def int_at_least(lowest: int, highest: int | None = None):
    """An integer in ``[lowest, highest]``."""
    bound = f">= {lowest}" if highest is None else f"in [{lowest}, {highest}]"

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be an integer {bound}, got {text!r}") from None
        if value < lowest or (highest is not None and value > highest):
            raise argparse.ArgumentTypeError(f"must be an integer {bound}, got {text}")
        return value

    return parse


def finite_float(lowest: float | None = None):
    """A finite number (``>= lowest`` if given): ``inf``, ``nan`` and ``1e309`` are refused."""
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not math.isfinite(value) or (lowest is not None and value < lowest):
            what = "a finite number" + (f" >= {lowest:g}" if lowest is not None else "")
            raise argparse.ArgumentTypeError(f"must be {what}, got {text!r}")
        return value

    return parse


def float_list(lowest: float | None = None):
    """Comma-separated finite numbers (at least one)."""
    one = finite_float(lowest)

    def parse(text: str) -> list[float]:
        parts = [p.strip() for p in text.split(",") if p.strip()]
        if not parts:
            raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}")
        try:
            return [one(p) for p in parts]
        except argparse.ArgumentTypeError as err:
            raise argparse.ArgumentTypeError(f"{err} (in {text!r})") from None

    return parse


def int_list(lowest: int):
    """Comma-separated integers ``>= lowest`` (at least one)."""
    one = int_at_least(lowest)

    def parse(text: str) -> list[int]:
        parts = [p.strip() for p in text.split(",") if p.strip()]
        if not parts:
            raise argparse.ArgumentTypeError(f"expected comma-separated integers >= {lowest}, got {text!r}")
        try:
            return [one(p) for p in parts]
        except argparse.ArgumentTypeError as err:
            raise argparse.ArgumentTypeError(f"{err} (in {text!r})") from None

    return parse


def grid(text: str) -> tuple[float, float, int]:
    """``START:STOP:NUM``: NUM evenly spaced values from START to STOP (``numpy.linspace``)."""
    parts = text.split(":")
    if len(parts) != 3:
        raise argparse.ArgumentTypeError(f"expected START:STOP:NUM, got {text!r}")
    try:
        start, stop = finite_float()(parts[0]), finite_float()(parts[1])
        num = int_at_least(1, 100_000)(parts[2])
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"expected START:STOP:NUM (finite START and STOP, an integer NUM in "
                                         f"[1, 100000]), got {text!r}") from None
    return start, stop, num


def names(kind: str, choices=None):
    """Comma-separated names (at least one; from ``choices()`` when given, looked up when used)."""
    def parse(text: str) -> list[str]:
        items = [p.strip() for p in text.split(",") if p.strip()]
        if not items:
            raise argparse.ArgumentTypeError(f"expected comma-separated {kind}, got {text!r}")
        if choices is not None:
            valid = list(choices())
            bad = [n for n in items if n not in valid]
            if bad:
                raise argparse.ArgumentTypeError(f"unknown {kind} {', '.join(bad)}; choose from {', '.join(valid)}")
        return items

    return parse


def one_of(kind: str, choices):
    """One name of ``choices()`` (looked up when the option is used)."""
    def parse(text: str) -> str:
        valid = list(choices())
        if text not in valid:
            raise argparse.ArgumentTypeError(f"unknown {kind} {text!r}; choose one of {', '.join(valid)}")
        return text

    return parse


#: the largest window ``--size`` accepts per side (the viewer renders at twice the size)
MAX_PIXELS = 8192


def window_size(text: str) -> str:
    """``WIDTHxHEIGHT`` in pixels, each in [64, MAX_PIXELS]; returned normalised (``1600x1000``)."""
    parts = text.lower().split("x")
    try:
        w, h = (int(p) for p in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT in pixels (e.g. 1600x1000), got {text!r}") from None
    if not (64 <= w <= MAX_PIXELS and 64 <= h <= MAX_PIXELS):
        raise argparse.ArgumentTypeError(f"each side must lie in [64, {MAX_PIXELS}] pixels, got {text!r}")
    return f"{w}x{h}"


def file_name(suffix: str):
    """A file name ending in ``suffix`` (e.g. ``.png``): what it will be is checked when it is written."""
    def parse(text: str) -> str:
        if not text.endswith(suffix) or text.endswith("/") or len(text) <= len(suffix):
            raise argparse.ArgumentTypeError(f"expected a file name ending in {suffix}, got {text!r}")
        return text

    return parse


def tables():
    from pipps.reporting.tables import TABLES

    return TABLES


def methods():
    from pipps.experiments.methods import METHODS

    return METHODS
