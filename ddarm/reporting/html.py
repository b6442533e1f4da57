"""A report's Markdown as one self-contained HTML page: its figures inside it, opening offline from anywhere.

The page is Python-Markdown's rendering (tables, fenced code, heading anchors) with every local image
embedded as a base64 data: URI and a short inline style sheet; it loads nothing else (no fonts, no
scripts, no network). Links to local files that are not embedded (bags/..., results.json) stay relative
links, re-rooted at the page's folder. A link or image whose target is missing is refused by name before
anything is written, so a page once written has no broken reference.

Raw HTML in the Markdown is shown as text, never passed through: a name from a URDF that reads
`<meta http-equiv="refresh" …>` would otherwise navigate the reader's browser (no Content-Security-Policy
stops a meta refresh). The report writers also escape every text from a file (ddarm.reporting.text), so that
report.md reads right in any Markdown viewer.
"""

from __future__ import annotations

import base64
import html
import mimetypes
import os
import secrets
from pathlib import Path
from urllib.parse import quote, unquote, urlsplit, urlunsplit

import markdown
from markdown.extensions import Extension
from markdown.treeprocessors import Treeprocessor

from ddarm.errors import DdarmError

# Readable tables and figures, in the reader's own system fonts (a web font would be a download).
STYLE = """
body { font-family: system-ui, sans-serif; line-height: 1.45; color: #1b1b1b; background: #fff; margin: 0; }
main { max-width: 72rem; margin: 0 auto; padding: 1rem 1.5rem 3rem; }
h1, h2, h3 { line-height: 1.2; }
table { border-collapse: collapse; margin: 0.8rem 0; font-size: 0.92rem; }
th, td { border: 1px solid #c8c8c8; padding: 0.25rem 0.6rem; text-align: left; vertical-align: top; }
th { background: #eef1f4; }
tbody tr:nth-child(even) { background: #f8f9fa; }
td { font-variant-numeric: tabular-nums; }
img { max-width: 100%; height: auto; }
code { font-family: ui-monospace, monospace; font-size: 0.9em; background: #f2f2f2; padding: 0 0.2em; }
pre { background: #f2f2f2; padding: 0.6rem; overflow-x: auto; }
pre code { padding: 0; }
"""

# The policy makes "loads nothing else" hold in the browser too, should any HTML ever get past the escaping.
PAGE = """<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta http-equiv="Content-Security-Policy" content="default-src 'none'; img-src data:; style-src 'unsafe-inline'">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>{title}</title>
<style>{style}</style>
</head>
<body>
<main>
{body}
</main>
</body>
</html>
"""


# Links that leave the page for the web or for mail; any other scheme (javascript:, data:, file:) is refused.
LINK_SCHEMES = ('http', 'https', 'mailto')


class HtmlReportError(DdarmError, ValueError):
    """A page that cannot be made whole: its Markdown unreadable, a link's or an image's target missing, an image
    that is not a local image file, a link of another scheme than LINK_SCHEMES, or the page unwritable; the text
    names the file."""


def markdown_to_html(markdown_path: Path | str, html_path: Path | str, title: str | None = None) -> Path:
    """Render the Markdown file `markdown_path` into the self-contained page `html_path` and return its path.

    Relative links and images are read relative to the Markdown's folder. Images are embedded (a local
    image file, or a data: URI as it is); links to local files or folders become relative to the page's
    folder; links of LINK_SCHEMES (https:, mailto:) and links within the page (#anchor) are kept as written.
    Raw HTML in the Markdown is shown as the text it is. `title` defaults to the first level-1 heading's
    text, else the Markdown file's name. `html_path` is replaced if it exists (the new page is moved over
    it whole, so a symlink there is replaced, not followed): it is derived from the Markdown, so a stale
    page is rendered again; its folder must exist.

    Raises:
        HtmlReportError (a ValueError): the Markdown file cannot be read, a link or image names a local
            file that does not exist, an image is not an image file, an image is not local (the page
            must open offline), a link has another scheme than LINK_SCHEMES, or the page cannot be
            written. No page, and no part of one, is written then.
    """
    source, page = Path(markdown_path), Path(html_path)
    try:
        text = source.read_text(encoding='utf-8')
    except OSError as error:
        raise HtmlReportError(f'{source}: cannot read the report: {error.strerror}') from error
    except UnicodeDecodeError as error:
        raise HtmlReportError(f'{source}: cannot read the report: not UTF-8 text ({error.reason})') from error
    renderer = markdown.Markdown(extensions=['tables', 'fenced_code', 'toc', _LocalTargets(source, page.parent)])
    # Without these two, an HTML block or an inline tag would reach the page as markup; now it is text, escaped.
    renderer.preprocessors.deregister('html_block')
    renderer.inlinePatterns.deregister('html')
    body = renderer.convert(text)
    if title is None:
        # toc's names are the headings' text, HTML-escaped, with inline markup such as `code` removed.
        heading = next((token['name'] for token in renderer.toc_tokens if token['level'] == 1), None)
        title = html.unescape(heading) if heading else source.name
    content = PAGE.format(title=html.escape(title), style=STYLE, body=body).encode('utf-8')
    # A new name of its own ('x': never one made meanwhile), moved over the page once whole.
    partial = page.with_name(f'.{page.name}.{secrets.token_hex(8)}.partial')
    try:
        file = partial.open('xb')
    except OSError as error:
        raise HtmlReportError(f'{page}: cannot write the page: {error.strerror}') from error
    try:
        with file:
            file.write(content)
        partial.replace(page)
    except OSError as error:
        partial.unlink()
        raise HtmlReportError(f'{page}: cannot write the page: {error.strerror}') from error
    return page


class _LocalTargets(Extension):
    """Embeds the images and re-roots the local links of one Markdown file rendered into a page in `page_folder`."""

    def __init__(self, source: Path, page_folder: Path) -> None:
        super().__init__()
        self.source, self.page_folder = source, page_folder

    def extendMarkdown(self, md: markdown.Markdown) -> None:  # noqa: N802 (Python-Markdown's name)
        # After 'inline' (20), which makes the <img> and <a> elements; before 'prettify' (10).
        md.treeprocessors.register(_TargetRewriter(md, self.source, self.page_folder), 'ddarm_local_targets', 15)


class _TargetRewriter(Treeprocessor):
    """_LocalTargets' pass over the rendered tree: every <img> embedded, every local <a href> checked and re-rooted."""

    def __init__(self, md: markdown.Markdown, source: Path, page_folder: Path) -> None:
        super().__init__(md)
        self.source, self.page_folder = source, page_folder

    def run(self, root) -> None:
        for element in root.iter('img'):
            element.set('src', self._embedded(element.get('src', '')))
        for element in root.iter('a'):
            if element.get('href') is not None:
                element.set('href', self._relinked(element.get('href')))

    def _local_target(self, kind: str, reference: str) -> Path | None:
        """The existing local file or folder `reference` names; None for a web address or a place on this page."""
        parts = urlsplit(reference)
        if parts.scheme or parts.netloc or not parts.path:
            return None
        path = Path(unquote(parts.path))
        target = path if path.is_absolute() else self.source.parent / path
        if not target.exists():
            raise HtmlReportError(f'{self.source}: {kind} {reference}: {target} does not exist')
        return target

    def _embedded(self, reference: str) -> str:
        if urlsplit(reference).scheme == 'data':
            return reference
        target = self._local_target('image', reference)
        if target is None:
            raise HtmlReportError(f'{self.source}: image {reference!r} is not a local file, and the page must '
                                  'open offline')
        mime = mimetypes.guess_type(target.name)[0]
        if not target.is_file() or not mime or not mime.startswith('image/'):
            raise HtmlReportError(f'{self.source}: image {reference}: {target} is not an image file')
        return f'data:{mime};base64,{base64.b64encode(target.read_bytes()).decode("ascii")}'

    def _relinked(self, reference: str) -> str:
        scheme = urlsplit(reference).scheme
        if scheme and scheme.lower() not in LINK_SCHEMES:
            raise HtmlReportError(f'{self.source}: link {reference!r}: a {scheme}: link, and a report links only '
                                  f'local files and {", ".join(f"{name}:" for name in LINK_SCHEMES)} addresses')
        target = self._local_target('link', reference)
        if target is None:
            return reference
        parts = urlsplit(reference)
        relative = Path(os.path.relpath(target.absolute(), self.page_folder.absolute())).as_posix()
        return urlunsplit(('', '', quote(relative), parts.query, parts.fragment))
