"""Dataclasses to and from JSON-like data, strictly: the one reader of results.json and settings.yaml.

A field's annotation is its contract. Every field is required and no other key is taken, so a stale or
mistyped file is refused rather than half read; a value must have its field's type (a float field takes
an int, a bool is never a number). A refusal names the key by its path, e.g. `table2[3].bag`. The one
exception is a renamed field's old name: an alias (`aliased`) written beside it, or a deprecated key
(`read`'s `renamed`) read in its place with a notice.
"""

from __future__ import annotations

import dataclasses
import types
from collections.abc import Mapping
from typing import Literal, Union, get_args, get_origin, get_type_hints

from ddarm.deprecation import renamed_keys
from ddarm.motion.files import shown

_ALIAS = 'alias'


def aliased(old: str):
    """A field also written as `old`, right after it with the same value, so that readers of the file who know it
    by its old name go on working; read from either key, or from both when they agree."""
    return dataclasses.field(metadata={_ALIAS: old})


def read(kind: type, data, source: str, error: type[Exception],
         renamed: Mapping[type, Mapping[str, str]] | None = None):
    """`data` as a `kind` (a dataclass); `error` names `source` and the key of anything refused. `renamed` gives,
    per dataclass, its deprecated keys (old: new), read as the new ones with a notice (ddarm.deprecation)."""
    return _Reader(source, error, renamed or {}).value(kind, data, '')


def write(value):
    """A dataclass as plain dicts, lists and scalars, in field order (json.dumps writes it as it is)."""
    if dataclasses.is_dataclass(value):
        written = {}
        for field in dataclasses.fields(value):
            written[field.name] = write(getattr(value, field.name))
            if _ALIAS in field.metadata:
                written[field.metadata[_ALIAS]] = written[field.name]
        return written
    if isinstance(value, Mapping):
        return {key: write(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [write(item) for item in value]
    return value


def _join(path: str, key) -> str:
    name = str(key) if not isinstance(key, str) or len(key) <= 80 else key[:80] + '…'  # a path for messages only
    return f'{path}.{name}' if path else name


class _Reader:
    def __init__(self, source: str, error: type[Exception], renamed: Mapping[type, Mapping[str, str]]) -> None:
        self.source, self.error, self.renamed = source, error, renamed

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
        if kind in self.renamed:
            data = renamed_keys(data, self.renamed[kind], f'{self.source}: {path}', self.error)
        data = self.unaliased(kind, data, path)
        names = [field.name for field in dataclasses.fields(kind)]
        for name in names:
            if name not in data:
                self.fail(f'missing key {_join(path, name)!r}')
        for key in data:
            if key not in names:
                self.fail(f'unknown key {_join(path, key)!r}')
        hints = get_type_hints(kind)
        return kind(**{name: self.value(hints[name], data[name], _join(path, name)) for name in names})

    def unaliased(self, kind: type, data: dict, path: str) -> dict:
        """`data` with each alias's value under its field's name. No notice: the alias is written beside the field
        (files written before the field had its name hold the alias only)."""
        for field in dataclasses.fields(kind):
            old = field.metadata.get(_ALIAS)
            if old is None or old not in data:
                continue
            data = dict(data)
            value = data.pop(old)
            if data.setdefault(field.name, value) != value:
                self.fail(f'{_join(path, field.name)} is {shown(data[field.name])} but its deprecated name '
                          f'{_join(path, old)} is {shown(value)}: the two must be equal')
        return data
