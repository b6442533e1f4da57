"""Text from files (joint, link and frame names, paths, commands, messages) shown as itself in a report or a figure.

A URDF, a motion file or a command line can hold any characters: Markdown or HTML syntax, a newline that
ends a table row, a bidirectional override that reorders the digits after it, a `$` that matplotlib takes for
mathematics. Every such text goes through one of these before it is written into a report (into a figure:
`figure_text`, drawn with parse_math=False), so that it can neither run, nor link, nor change the layout, nor pass
for another text: it reads as the characters it has.
"""

from __future__ import annotations

import re
import unicodedata

# Line breaks, other controls, format characters (bidirectional overrides, zero-width ones), separators,
# surrogates and private or unassigned code points: each shown by name, as nothing on the page is invisible.
_INVISIBLE_CATEGORIES = frozenset(('Cc', 'Cf', 'Cs', 'Co', 'Cn', 'Zl', 'Zp'))
# What starts emphasis, code, a link or a table cell inline; Python-Markdown and CommonMark both take a
# backslash before each of them as the character itself.
_MARKDOWN_PUNCTUATION = frozenset('\\`*_[]|')
# What CommonMark or GitHub reads inline but Python-Markdown cannot backslash-escape: a character reference
# is the character itself in both (an HTML tag, an entity, strikethrough, GitHub's mathematics).
_REFERENCES = {'&': '&amp;', '<': '&lt;', '~': '&#126;', '$': '&#36;'}
_BACKTICKS = re.compile('`+')
_PLAIN_ASCII = re.compile('[\n\t\x20-\x7e]*')
# A message's words longer than this (a joint name of megabytes from a file) are shown by their ends: a message
# names a thing for a person to find it, and a path or a name this long is found by its start and end.
LONGEST_WORD = 500
_LONG_WORD = re.compile(r'\S{%d,}' % (LONGEST_WORD + 1))


def visible(text, pictures: bool = True) -> str:
    """`text` (str() of it) on one line with every invisible character shown: a control as its Unicode control
    picture (a newline as ␊) if `pictures`, any other (or every one, without `pictures`) as <U+XXXX>."""
    shown = []
    for character in str(text):
        if unicodedata.category(character) not in _INVISIBLE_CATEGORIES:
            shown.append(character)
        elif pictures and ord(character) < 0x20:
            shown.append(chr(0x2400 + ord(character)))
        elif pictures and character == '\x7f':
            shown.append('\u2421')
        else:
            shown.append(f'<U+{ord(character):04X}>')
    return ''.join(shown)


def terminal_text(text) -> str:
    """`text` (str() of it) for a terminal: every invisible character but a line feed or a tab shown as
    <U+XXXX>. An escape sequence in a joint name or a path (ESC [ 2 J) would otherwise clear the screen, retitle
    the window or rewrite the lines printed before it."""
    text = str(text)
    if _PLAIN_ASCII.fullmatch(text):
        return text
    return ''.join(character if character in '\n\t' or unicodedata.category(character) not in _INVISIBLE_CATEGORIES
                   else f'<U+{ord(character):04X}>' for character in text)


def shortened(text) -> str:
    """`text` (str() of it) with every run of more than LONGEST_WORD non-space characters cut to its first 200 and
    last 100, the count of those left out between them: a message stays a message, whatever it names."""
    return _LONG_WORD.sub(lambda word: f'{word[0][:200]}…<{len(word[0]) - 300} characters>…{word[0][-100:]}',
                          str(text))


def figure_text(text) -> str:
    """`text` for a matplotlib label drawn with parse_math=False: visible, in ASCII where it was invisible (the
    figures' fonts have no control pictures)."""
    return visible(text, pictures=False)


def markdown_text(text) -> str:
    """Markdown that renders as `text` (str() of it), literally and on one line, also inside a table cell."""
    shown = visible(text)
    escaped = []
    for at, character in enumerate(shown):
        if character in _REFERENCES:
            escaped.append(_REFERENCES[character])
        elif character == '_' and shown[at - 1:at].isalnum() and shown[at + 1:at + 2].isalnum():
            escaped.append(character)  # within a word, as in computed_torque, _ is never emphasis: left readable
        elif character in _MARKDOWN_PUNCTUATION:
            escaped.append('\\' + character)
        else:
            escaped.append(character)
    return ''.join(escaped)


# What opens a block when a line starts with it: a heading, a quote, a list item or a thematic break. A numbered
# item (1. or 1)) is opened by its digits' following . or ).
_BLOCK_OPENERS = frozenset('#>-+')
_NUMBERED_ITEM = re.compile(r'(\d+)([.)])')


def markdown_paragraph(text) -> str:
    """Markdown that renders as `text` (str() of it) in a paragraph of its own: markdown_text, and what would
    open another block at the line's start (a heading, quote, list, thematic break, indented code) taken as text."""
    escaped = markdown_text(text).lstrip(' ')  # leading spaces: a paragraph drops up to 3; 4 open a code block
    if escaped[:1] in _BLOCK_OPENERS:
        return '\\' + escaped
    return _NUMBERED_ITEM.sub(r'\1\\\2', escaped, count=1) if _NUMBERED_ITEM.match(escaped) else escaped


def markdown_code(text) -> str:
    """A Markdown code span that renders as `text` (str() of it), literally and on one line; not for table cells,
    where GitHub would split it at a |."""
    shown = visible(text)
    fence = '`' * (1 + max((len(run) for run in _BACKTICKS.findall(shown)), default=0))
    # Spaced off a backtick at either end, which would otherwise join the fence; renderers strip the spaces.
    padding = ' ' if shown[:1] == '`' or shown[-1:] == '`' or not shown.strip() else ''
    return f'{fence}{padding}{shown}{padding}{fence}'


class TerminalStream:
    """A text stream that writes what it is given through terminal_text to `target`: everything a command prints
    (tables, messages, warnings) holds names and paths from files. `target` stays reachable for a progress bar,
    whose own carriage returns and escapes must reach the terminal. `messages`: the stream carries messages only
    (stderr), never data, so their overlong words are `shortened`."""

    def __init__(self, target, messages: bool = False) -> None:
        self.target = target
        self.messages = messages

    def write(self, text: str) -> int:
        self.target.write(terminal_text(shortened(text) if self.messages else text))
        return len(text)

    def __getattr__(self, name: str):
        return getattr(self.target, name)
