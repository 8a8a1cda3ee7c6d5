"""Numbers in data files, read by the C locale grammar (what ``strtod`` / ``strtol`` accept).

Python's ``float()`` and ``int()`` read more than the files' own tools do: digit-group underscores
(``1_000``), any Unicode decimal digit (Arabic-Indic ``٣``) and, for ``int``, surrounding white
space. A g2o file, a CARMEN log or a TUM trajectory is written and read by C and C++ programs, so a
token they would not read as a number is refused here too: ASCII only, no ``_``. What remains is
exactly the decimal ``strtod`` grammar of a whole token (sign, digits, ``.``, exponent, ``inf``/``infinity``/``nan``);
hexadecimal floats are refused (no file of these formats uses them).
"""

from __future__ import annotations

import re

__all__ = ["c_float", "c_int", "c_floats"]

_INT = re.compile(r"[+-]?[0-9]+")
_INT_B = re.compile(rb"[+-]?[0-9]+")


def _lax(tok: str | bytes) -> bool:
    """True when Python would read *tok* although the C grammar does not (non-ASCII, ``_``, white space
    around it)."""
    return not tok.isascii() or (b"_" if isinstance(tok, bytes) else "_") in tok or tok.strip() != tok


def c_float(tok: str | bytes) -> float:
    """``float(tok)`` by the C locale grammar; raises ValueError otherwise (non-finite values pass)."""
    if _lax(tok):
        raise ValueError(f"not a number: {tok!r}")
    return float(tok)


def c_int(tok: str | bytes) -> int:
    """``int(tok)`` by the C locale grammar (optional sign, ASCII digits); raises ValueError otherwise."""
    pattern = _INT_B if isinstance(tok, bytes) else _INT
    if pattern.fullmatch(tok) is None:
        raise ValueError(f"not an integer: {tok!r}")
    return int(tok)


def c_floats(tokens: list[str] | list[bytes]) -> list[float]:
    """:func:`c_float` of every token; the ValueError names the first token that is not a number."""
    try:
        if not any(_lax(t) for t in tokens):
            return [float(t) for t in tokens]
    except ValueError:
        pass
    for t in tokens:
        c_float(t)
    raise AssertionError("unreachable")  # pragma: no cover - the loop raised
