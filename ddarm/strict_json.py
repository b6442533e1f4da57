"""JSON as the standard has it: a report or summary holding inf or nan is refused by the place of the number,
never written as Infinity or NaN, which no strict reader parses. The lowest layer: commands and run folders share
it."""

from __future__ import annotations

import json
import math

from ddarm.errors import DdarmError


class OutputError(DdarmError, ValueError):
    """A report holding a number JSON cannot (inf, nan): a bug upstream, refused rather than printed."""


def non_finite_fields(value, path: str = '') -> list[str]:
    """The places (`a.b[2]`) of every float in `value` (dicts, lists, tuples) that is inf or nan."""
    if isinstance(value, float):
        return [] if math.isfinite(value) else [f'{path or "the value"} = {value}']
    if isinstance(value, dict):
        return [place for key, item in value.items() for place in non_finite_fields(item, f'{path}.{key}'
                                                                                     if path else str(key))]
    if isinstance(value, (list, tuple)):
        return [place for i, item in enumerate(value) for place in non_finite_fields(item, f'{path}[{i}]')]
    return []


def json_text(report, indent: int | None = None) -> str:
    """`report` as JSON the standard accepts: a non-finite number is refused by its place, never written as
    Infinity or NaN (which no strict reader parses)."""
    places = non_finite_fields(report)
    if places:
        raise OutputError(f"the report holds numbers JSON cannot: {', '.join(places[:5])}"
                          + (f' and {len(places) - 5} more' if len(places) > 5 else ''))
    return json.dumps(report, allow_nan=False, indent=indent)
