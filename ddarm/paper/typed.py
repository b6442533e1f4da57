"""Dataclasses to and from JSON-like data, strictly: the one reader of results.json and settings.yaml.

A field's annotation is its contract. Every field is required and no other key is taken, so a stale or
mistyped file is refused rather than half read; a value must have its field's type (a float field takes
an int, a bool is never a number). A refusal names the key by its path, e.g. `table2[3].bag`.
"""

from __future__ import annotations

import dataclasses
import types
from collections.abc import Mapping
from typing import Literal, Union, get_args, get_origin, get_type_hints

from ddarm.motion.files import shown


def read(kind: type, data, source: str, error: type[Exception]):
    """`data` as a `kind` (a dataclass); `error` names `source` and the key of anything refused."""
    return _Reader(source, error).value(kind, data, '')


def write(value):
    """A dataclass as plain dicts, lists and scalars, in field order (json.dumps writes it as it is)."""
    if dataclasses.is_dataclass(value):
        return {field.name: write(getattr(value, field.name)) for field in dataclasses.fields(value)}
    if isinstance(value, Mapping):
        return {key: write(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [write(item) for item in value]
    return value


def _join(path: str, key) -> str:
    name = str(key) if not isinstance(key, str) or len(key) <= 80 else key[:80] + '…'  # a path for messages only
    return f'{path}.{name}' if path else name


class _Reader:
    def __init__(self, source: str, error: type[Exception]) -> None:
        self.source, self.error = source, error

    def fail(self, message: str):
        raise self.error(f'{self.source}: {message}')

    def value(self, kind, data, path: str):
        origin, arguments = get_origin(kind), get_args(kind)
        if dataclasses.is_dataclass(kind):
            return self.record(kind, data, path)
        if origin in (Union, types.UnionType):  # only `X | None` is used
            if data is None and type(None) in arguments:
                return None
            (other,) = (argument for argument in arguments if argument is not type(None))
            return self.value(other, data, path)
        if origin is Literal:
            if isinstance(data, bool) or data not in arguments:
                self.fail(f'{path} must be one of {arguments}, got {shown(data)}')
            return data
        if origin in (tuple, list):
            if not isinstance(data, list):
                self.fail(f'{path} must be a list, got {shown(data)}')
            items = [self.value(arguments[0], item, f'{path}[{i}]') for i, item in enumerate(data)]
            return tuple(items) if origin is tuple else items
        if origin in (dict, Mapping):
            if not isinstance(data, dict):
                self.fail(f'{path} must be a mapping, got {shown(data)}')
            key_kind, item_kind = arguments
            # Read-only: the settings are frozen all the way down.
            return types.MappingProxyType({self.value(key_kind, key, f'{_join(path, key)} (a key)'):
                                           self.value(item_kind, item, _join(path, key))
                                           for key, item in data.items()})
        if kind is float:
            if isinstance(data, bool) or not isinstance(data, (int, float)):
                self.fail(f'{path} must be a number, got {shown(data)}')
            return float(data)
        if kind in (int, bool, str):
            if not isinstance(data, kind) or (kind is int and isinstance(data, bool)):
                self.fail(f'{path} must be {kind.__name__}, got {shown(data)}')
            return data
        raise TypeError(f'{path}: no reader for {kind!r}')

    def record(self, kind: type, data, path: str):
        if not isinstance(data, dict):
            self.fail(f'{path or "the top level"} must be a mapping, got {type(data).__name__}')
        names = [field.name for field in dataclasses.fields(kind)]
        for name in names:
            if name not in data:
                self.fail(f'missing key {_join(path, name)!r}')
        for key in data:
            if key not in names:
                self.fail(f'unknown key {_join(path, key)!r}')
        hints = get_type_hints(kind)
        return kind(**{name: self.value(hints[name], data[name], _join(path, name)) for name in names})
