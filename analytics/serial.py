"""Reading a result back from its JSON form (the ``from_dict`` of the result types)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from analytics.errors import DataError

__all__ = ["Reader"]


class Reader:
    """The fields of one mapping of a result's JSON form, naming what is missing and where.

    >>> Reader({"a": 1}, "diagnosis")("b")
    Traceback (most recent call last):
    ...
    analytics.errors.DataError: diagnosis: the field 'b' is missing
    """

    def __init__(self, d: Any, where: str) -> None:
        if not isinstance(d, Mapping):
            raise DataError(f"{where}: expected an object, got {type(d).__name__}")
        self.d, self.where = d, where

    def __call__(self, key: str) -> Any:
        if key not in self.d:
            raise DataError(f"{self.where}: the field {key!r} is missing")
        return self.d[key]

    def get(self, key: str) -> Any:
        """The field, or None where it is missing (a field later versions added)."""
        return self.d.get(key)

    def part(self, key: str) -> Reader:
        """The mapping under ``key``."""
        return Reader(self(key), f"{self.where}.{key}")

    def items(self, key: str) -> list[Reader]:
        """The mappings of the list under ``key``."""
        values = self(key)
        if not isinstance(values, list | tuple):
            raise DataError(f"{self.where}.{key}: expected a list, got {type(values).__name__}")
        return [Reader(v, f"{self.where}.{key}[{i}]") for i, v in enumerate(values)]

    def pair(self, key: str) -> tuple[Any, Any]:
        """The two values of the list under ``key``."""
        values = self(key)
        if not isinstance(values, list | tuple) or len(values) != 2:
            raise DataError(f"{self.where}.{key}: expected a pair, got {values!r}")
        return values[0], values[1]
