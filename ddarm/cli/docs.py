"""docs/cli.md, generated from `ddarm`'s argument parser: every command, its options, their defaults and help.

    .venv/bin/python -m ddarm.cli.docs        # rewrites docs/cli.md (make docs)

The page is read from the parser itself (each subparser's actions), never written by hand, so that it cannot
drift from what `ddarm` takes; test_docs.py fails when the committed page differs from this output.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ddarm.cli.main import build_parser

PAGE = Path(__file__).resolve().parents[2] / 'docs' / 'cli.md'


def _cell(text: str) -> str:
    """Text inside a Markdown table cell: one line, its pipes escaped."""
    return ' '.join(str(text).split()).replace('|', '\\|')


def _names(action: argparse.Action) -> str:
    if not action.option_strings:
        return f'`{action.metavar or action.dest}`'
    value = ''
    if action.nargs != 0:
        if action.choices is not None:
            value = ' {' + ','.join(map(str, action.choices)) + '}'
        else:
            value = f' {action.metavar or action.dest.upper()}'
        if action.nargs in ('+', '*'):
            value += ' …'
    return ', '.join(f'`{name}{value}`' for name in action.option_strings)


def _default(action: argparse.Action) -> str:
    if action.nargs == 0 or action.default in (None, argparse.SUPPRESS):
        return ''
    if isinstance(action.default, (list, tuple)):
        return ' '.join(map(str, action.default))
    return str(action.default)


def _commands(parser: argparse.ArgumentParser) -> dict[str, tuple[str, argparse.ArgumentParser]]:
    """Each subcommand's help line and parser, in the order `ddarm --help` lists them."""
    (subparsers,) = [action for action in parser._actions if isinstance(action, argparse._SubParsersAction)]
    helps = {choice.dest: choice.help for choice in subparsers._choices_actions}
    return {name: (helps.get(name, ''), command) for name, command in subparsers.choices.items()}


def cli_reference() -> str:
    """The page's text."""
    parser = build_parser()
    commands = _commands(parser)
    lines = ['# `ddarm` command line', '',
             'Generated from the argument parser by `make docs` (`python -m ddarm.cli.docs`); do not edit by hand. '
             'Every command also takes `--help`.', '',
             *(f'- [`ddarm {name}`](#ddarm-{name}): {_cell(help_line)}' for name, (help_line, _) in commands.items())]
    for name, (help_line, command) in commands.items():
        lines += ['', f'## ddarm {name}', '', _cell(help_line), '', '| option | default | meaning |', '|---|---|---|']
        for action in command._actions:
            if isinstance(action, argparse._HelpAction):
                continue
            required = ' (required)' if action.required and action.option_strings else ''
            lines.append(f'| {_names(action)} | {_cell(_default(action))} | {_cell(action.help or "")}{required} |')
    return '\n'.join(lines) + '\n'


def main() -> int:
    PAGE.parent.mkdir(exist_ok=True)
    PAGE.write_text(cli_reference())
    print(f'{PAGE}: {len(_commands(build_parser()))} commands')
    return 0


if __name__ == '__main__':
    sys.exit(main())
