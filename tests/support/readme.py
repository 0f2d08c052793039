"""The printed outputs README.md shows, checked against what maglog prints."""

import re
from pathlib import Path

README = Path(__file__).resolve().parents[2] / "README.md"
NUMBER = re.compile(r"[-+]?\d+(?:\.\d+)?(?:e[-+]?\d+)?")


def readme_verdicts():
    """The Verdicts block of the README's "as printed" end of ``make run``."""
    text = README.read_text(encoding="utf-8")
    match = re.search(r"as\s+printed:\n\n```\n(Verdicts\n.*?)```", text, re.S)
    assert match, "README.md has no printed Verdicts block after 'as printed:'"
    return match.group(1).strip("\n")


def printed_verdicts(output):
    """The Verdicts block of a run's printed summary."""
    match = re.search(r"^(Verdicts\n(?:  .*\n?)+)", output, re.M)
    assert match, f"no Verdicts block in the output:\n{output[-2000:]}"
    return match.group(1).strip("\n")


def same_printout(shown, printed, rel=0.1, abs_=0.05):
    """None when ``printed`` reads as ``shown``: the same words, the same integers, and
    floats within ``rel`` (or ``abs_``) of each other, since the last digits of a fit follow
    the machine's BLAS; otherwise the first line that differs."""
    shown_lines, printed_lines = shown.splitlines(), printed.splitlines()
    if len(shown_lines) != len(printed_lines):
        return f"{len(printed_lines)} lines printed, {len(shown_lines)} shown"
    for a, b in zip(shown_lines, printed_lines):
        if NUMBER.sub("#", a) != NUMBER.sub("#", b):
            return f"shown:   {a}\nprinted: {b}"
        for x, y in zip(NUMBER.findall(a), NUMBER.findall(b)):
            if "." not in x + y and "e" not in x + y:
                if x != y:
                    return f"shown:   {a}\nprinted: {b}"
            elif abs(float(x) - float(y)) > max(abs_, rel * abs(float(x))):
                return f"shown:   {a}\nprinted: {b}"
    return None
