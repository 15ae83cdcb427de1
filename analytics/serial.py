"""Reading a result back from its JSON form (the ``from_dict`` of the result types)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import MISSING, fields
from typing import Any, TypeVar

from analytics.errors import DataError

__all__ = ["Reader"]

T = TypeVar("T")


class Reader:
    """The fields of one mapping of a result's JSON form, naming what is missing and where.

    A strict reader refuses a missing field; a ``lenient`` one (results stored by older
    versions, which lack the fields added since) reads it as its ``default`` (None
    unless given), a missing or null mapping as an empty one and a missing or null list
    as empty.

    >>> Reader({"a": 1}, "diagnosis")("b")
    Traceback (most recent call last):
    ...
    analytics.errors.DataError: diagnosis: the field 'b' is missing
    >>> old = Reader({"a": 1}, "diagnosis", lenient=True)
    >>> old("b", 0.0), old.part("c").get("d"), old.items("e")
    (0.0, None, [])
    """

    def __init__(self, d: Any, where: str, *, lenient: bool = False) -> None:
        if lenient and d is None:
            d = {}
        if not isinstance(d, Mapping):
            raise DataError(f"{where}: expected an object, got {type(d).__name__}")
        self.d, self.where, self.lenient = d, where, lenient

    def __call__(self, key: str, default: Any = None) -> Any:
        """The field; where it is missing, ``default`` for a lenient reader."""
        if key not in self.d:
            if self.lenient:
                return default
            raise DataError(f"{self.where}: the field {key!r} is missing")
        return self.d[key]

    def get(self, key: str) -> Any:
        """The field, or None where it is missing (a field later versions added)."""
        return self.d.get(key)

    def part(self, key: str) -> Reader:
        """The mapping under ``key``."""
        return Reader(self(key), f"{self.where}.{key}", lenient=self.lenient)

    def items(self, key: str) -> list[Reader]:
        """The mappings of the list under ``key``."""
        values = self(key)
        if values is None and self.lenient:
            return []
        if not isinstance(values, list | tuple):
            raise DataError(f"{self.where}.{key}: expected a list, got {type(values).__name__}")
        return [Reader(v, f"{self.where}.{key}[{i}]", lenient=self.lenient)
                for i, v in enumerate(values)]

    def pair(self, key: str) -> tuple[Any, Any]:
        """The two values of the list under ``key``."""
        values = self(key)
        if not isinstance(values, list | tuple) or len(values) != 2:
            raise DataError(f"{self.where}.{key}: expected a pair, got {values!r}")
        return values[0], values[1]

    def flat(self, cls: type[T]) -> T:
        """The dataclass ``cls`` whose fields are all plain values (numbers, texts),
        each read under its own name; a lenient reader gives a missing one the field's
        default (None where it has none).

        >>> from analytics.kpi import HarrisIndex
        >>> Reader({"mv_variance": 1.0, "mse": 4.0, "ratio": 4.0, "normalised": 0.75,
        ...         "dead_time": 3}, "harris").flat(HarrisIndex).normalised
        0.75
        """
        return cls(**{f.name: self(f.name, None if f.default is MISSING else f.default)
                      for f in fields(cls)})  # type: ignore[arg-type]
