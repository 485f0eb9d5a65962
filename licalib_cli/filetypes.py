"""Values read back from licalib's own YAML files, checked against their declared types.

A result file or a ``truth.yaml`` may have been edited by hand or cut short. Every value read
from one is checked against the annotation of the field it fills (or the shape the array
must have), and a wrong one ends in a :class:`FileValueError` naming its key, e.g.::

    `consistency.split_half.compared` is 5, not a list of strings

which the file's loader turns into one sentence naming the file and the fix.

==========================  ===========================================================
annotation                  accepted
==========================  ===========================================================
``float``                   an integer or a float (YAML ``.inf`` / ``.nan`` included;
                            ``null``, the JSON export's non-finite number, reads as NaN)
``int``                     an integer
``str`` / ``bool``          a string / ``true`` or ``false``
``X | None``                ``null`` or an ``X``
``tuple[X, ...]``           a list of ``X``
``tuple[X, Y, Z]``          a list of exactly three, each of its type
``dict[str, X]``            a mapping from strings to ``X``
a section                   a mapping read by the section's ``from_dict``
==========================  ===========================================================
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from typing import Any

import numpy as np
import numpy.typing as npt

from licalib_cli.errors import ConfigError

__all__ = [
    "FileValueError",
    "described",
    "field_types",
    "joined",
    "number",
    "numbers",
    "typed",
    "wrong",
]


class FileValueError(ConfigError):
    """A value of a licalib file is missing or not of its type.

    Attributes:
        key: the dotted key, list positions included (``consistency.sensors.0.name``).
        problem: what is wrong, e.g. ``is 5, not a list of strings`` or ``is missing``.
    """

    def __init__(self, key: str, problem: str) -> None:
        self.key = key
        self.problem = problem
        super().__init__(f"`{key}` {problem}; {_FIX}.")

    def in_file(self, what: str) -> ConfigError:
        """The same finding as one sentence naming the file (``what``: e.g. ``the result file
        out/result.yaml``)."""
        return ConfigError(f"In {what}, `{self.key}` {self.problem}; {_FIX}.")


_FIX = "correct that key or regenerate the file with this licalib version"


def _shown(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def wrong(key: str, value: Any, expected: str) -> FileValueError:
    """The error for ``value`` under ``key`` that is not ``expected``."""
    return FileValueError(key, f"is {_shown(value)}, not {expected}")


def joined(key: str, sub: str | int) -> str:
    """``key.sub`` (``sub`` alone at the top)."""
    return f"{key}.{sub}" if key else str(sub)


def _is_section(hint: Any) -> bool:
    return isinstance(hint, type) and hasattr(hint, "from_dict")


def _members(hint: Any) -> tuple[Any, ...]:
    return typing.get_args(hint)


def _is_union(hint: Any) -> bool:
    return typing.get_origin(hint) in (typing.Union, types.UnionType)


def described(hint: Any) -> str:
    """The annotation in words (``a list of 3 numbers``, ``a string or null``)."""
    if hint is float:
        return "a number"
    if hint is int:
        return "a whole number"
    if hint is str:
        return "a string"
    if hint is bool:
        return "true or false"
    if hint is type(None):
        return "null"
    if _is_section(hint):
        return "a mapping"
    if _is_union(hint):
        return " or ".join(described(h) for h in _members(hint))
    origin, args = typing.get_origin(hint), _members(hint)
    if origin is tuple:
        if len(args) == 2 and args[1] is Ellipsis:
            return f"a list of {_plural(args[0])}"
        if len(set(args)) == 1:
            return f"a list of {len(args)} {_plural(args[0])}"
        return f"a list of {len(args)}"
    if origin is dict:
        return f"a mapping of names to {_plural(args[1])}"
    return "a value of its kind"


def _plural(hint: Any) -> str:
    words = {float: "numbers", int: "whole numbers", str: "strings", bool: "booleans"}
    if hint in words:
        return words[hint]
    if _is_section(hint):
        return "mappings"
    if _is_union(hint):
        return " or ".join(_plural(h) if h is not type(None) else "null" for h in _members(hint))
    return described(hint).removeprefix("a ").removeprefix("an ") + "s"


def number(value: Any, key: str, finite: bool = False) -> float:
    """``value`` as a float (an int, a float, or YAML's ``.inf`` / ``.nan`` read as one;
    ``finite``: not those)."""
    if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
        raise wrong(key, value, "a finite number" if finite else "a number")
    if finite and not np.isfinite(value):
        raise wrong(key, value, "a finite number")
    return float(value)


def numbers(value: Any, key: str, size: int | None = None, finite: bool = False) -> npt.NDArray:
    """``value`` as a float array: a list of numbers (of ``size``; all finite when asked)."""
    expected = f"a list of {size} numbers" if size is not None else "a list of numbers"
    if not isinstance(value, list | tuple) or (size is not None and len(value) != size):
        raise wrong(key, value, expected)
    out = np.array([number(v, joined(key, i)) for i, v in enumerate(value)], dtype=np.float64)
    if finite and not np.all(np.isfinite(out)):
        raise wrong(key, value, f"{expected}, all finite")
    return out


def typed(value: Any, hint: Any, key: str) -> Any:
    """``value`` checked against ``hint`` (lists become tuples, sections are read).

    Raises:
        FileValueError: it is not of that type.
    """
    if hint is Any:
        return value
    if _is_union(hint):
        members = _members(hint)
        if value is None and type(None) in members:
            return None
        for member in members:
            if member is type(None):
                continue
            try:
                return typed(value, member, key)
            except FileValueError:
                continue
        raise wrong(key, value, described(hint))
    if hint is float:
        return math.nan if value is None else number(value, key)
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise wrong(key, value, "a whole number")
        return value
    if hint in (str, bool):
        if not isinstance(value, hint):
            raise wrong(key, value, described(hint))
        return value
    if _is_section(hint):
        if not isinstance(value, dict):
            raise wrong(key, value, "a mapping")
        return hint.from_dict(value, key)
    origin, args = typing.get_origin(hint), _members(hint)
    if origin is tuple:
        if not isinstance(value, list | tuple):
            raise wrong(key, value, described(hint))
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(typed(v, args[0], joined(key, i)) for i, v in enumerate(value))
        if len(value) != len(args):
            raise wrong(key, value, described(hint))
        return tuple(
            typed(v, h, joined(key, i)) for i, (v, h) in enumerate(zip(value, args, strict=True))
        )
    if origin is dict:
        if not isinstance(value, dict):
            raise wrong(key, value, described(hint))
        return {typed(k, args[0], key): typed(v, args[1], joined(key, k)) for k, v in value.items()}
    msg = f"no reader for the annotation {hint!r}"
    raise TypeError(msg)


_FIELD_TYPES: dict[Any, dict[str, tuple[Any, bool]]] = {}


def field_types(cls: Any) -> dict[str, tuple[Any, bool]]:
    """Each dataclass field's resolved annotation and whether it is required (no default)."""
    if cls in _FIELD_TYPES:
        return _FIELD_TYPES[cls]
    hints = typing.get_type_hints(cls)
    _FIELD_TYPES[cls] = {
        f.name: (
            hints[f.name],
            f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING,
        )
        for f in dataclasses.fields(cls)
    }
    return _FIELD_TYPES[cls]
