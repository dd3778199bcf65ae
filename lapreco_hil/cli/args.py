"""The CLI's argument types, one per kind of number with its range, and a parser whose errors are one line.

Every numeric option of every subcommand takes one of these as its ``type=``, so a bad number is refused by
argparse, before any work, as ``lapreco: error: --fps: ...`` with exit status 2."""

from __future__ import annotations

import argparse
import math
import sys


class ArgumentParser(argparse.ArgumentParser):
    """argparse's errors as ONE line, ``lapreco: error: <option>: <what is wrong>``, exit status 2 (no usage
    dump: ``lapreco <command> --help`` has it). Subcommand parsers are of this class too."""

    def error(self, message: str):
        if message.startswith("argument "):
            message = message[len("argument "):]
        self.exit(2, f"lapreco: error: {message}\n")


def _bound(v) -> str:
    return str(v) if isinstance(v, int) else f"{v:g}"


def _range_text(ge=None, gt=None, le=None) -> str:
    low = f">= {_bound(ge)}" if ge is not None else f"> {_bound(gt)}" if gt is not None else None
    if low and le is not None:
        return f"{low} and <= {_bound(le)}"
    return low or (f"<= {_bound(le)}" if le is not None else "finite")


def integer(*, ge: int | None = None, le: int | None = None):
    """An argparse type: a whole number in [ge, le]."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"'{text}' is not a whole number (must be "
                                             f"{_range_text(ge=ge, le=le)})") from None
        if (ge is not None and value < ge) or (le is not None and value > le):
            raise argparse.ArgumentTypeError(f"{value} is out of range: must be {_range_text(ge=ge, le=le)}")
        return value

    parse.__name__ = "integer"
    return parse


def number(*, ge: float | None = None, gt: float | None = None, le: float | None = None):
    """An argparse type: a finite number (never nan or inf) with ``>= ge`` or ``> gt``, and ``<= le``."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = math.nan if text.strip().lower() == "nan" else None
        if value is None or not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"'{text}' is not a finite number (must be "
                                             f"{_range_text(ge, gt, le)})")
        if (ge is not None and value < ge) or (gt is not None and value <= gt) or (le is not None and value > le):
            raise argparse.ArgumentTypeError(f"{text} is out of range: must be {_range_text(ge, gt, le)}")
        return value

    parse.__name__ = "number"
    return parse


positive_int = integer(ge=1)  # counts: frames, features, repeats
seed = integer(ge=0, le=2**31 - 1)  # the simulator's random streams take a non-negative 32-bit seed
positive = number(gt=0.0)  # rates, durations, speeds, radii
non_negative = number(ge=0.0)  # periods where 0 means off
finite = number()  # signed offsets (ms)


def number_list(*, ge: float | None = None, gt: float | None = None, le: float | None = None):
    """An argparse type: comma-separated finite numbers, each in the range of ``number``."""
    one = number(ge=ge, gt=gt, le=le)

    def parse(text: str) -> list[float]:
        items = [t.strip() for t in text.split(",")]
        if not all(items):
            raise argparse.ArgumentTypeError(f"'{text}' must be comma-separated numbers, e.g. 0,20,40")
        return [one(t) for t in items]

    parse.__name__ = "number list"
    return parse


def resolution(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' must look like 640x480") from None
    if not (64 <= w <= 8192 and 64 <= h <= 8192):
        raise argparse.ArgumentTypeError(f"'{text}' is out of range: 64..8192 pixels per side")
    return w, h


def fail(message: str) -> int:
    """One error line on stderr; the CLI's exit status for a refused input."""
    print(f"lapreco: error: {message}", file=sys.stderr)
    return 2
