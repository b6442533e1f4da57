"""Old names, still read: a parameter, file key or option renamed so that one quantity has one name everywhere.

The old name keeps working, with a one-line notice naming the new one (DeprecatedName, a FutureWarning: shown to
users by default), so that a user's scripts, parameter files and campaign files go on running.
"""

import sys
import warnings
from collections.abc import Mapping


class DeprecatedName(FutureWarning):
    """An old name of a parameter, file key or option: still accepted, the message names the one to use."""


def deprecation_notice(old: str, new: str, where: str) -> str:
    """The one line that says `old` is read as `new` (a node logs it)."""
    return f'{where}: {old!r} is deprecated, read as {new!r} (give {new!r} instead)'


def deprecated_name(old: str, new: str, where: str) -> None:
    """Warn (once per place, as Python's warnings do) that `old` is read as `new`."""
    warnings.warn(deprecation_notice(old, new, where), DeprecatedName, stacklevel=3)


def one_line_deprecations() -> None:
    """Print DeprecatedName warnings as one line on stderr (`ddarm: deprecated: …`), not Python's two."""
    shown = warnings.showwarning

    def show(message, category, filename, lineno, file=None, line=None):
        if issubclass(category, DeprecatedName):
            print(f'ddarm: deprecated: {message}', file=file or sys.stderr)
        else:
            shown(message, category, filename, lineno, file, line)

    warnings.showwarning = show


def renamed_keys(mapping: Mapping, renames: Mapping[str, str], where: str, refused: type[Exception]) -> dict:
    """`mapping` (a file's) with each deprecated key of `renames` (old: new) under its new name, with a notice;
    `refused` names both when the file gives them different values."""
    renamed = dict(mapping)
    for old, new in renames.items():
        if old not in renamed:
            continue
        value = renamed.pop(old)
        if new in renamed and renamed[new] != value:
            raise refused(f'{where}: {new} given twice, as {new} ({renamed[new]!r}) and by its deprecated name {old} '
                          f'({value!r}): give {new} only')
        deprecated_name(old, new, where)
        renamed[new] = value
    return renamed
