"""Render the package's plain-text docstrings as reStructuredText without warnings.

The docstrings are written to be read in a terminal (``help()``, an editor): formulas in plain
text (``|det phi|``, ``c_ab``, ``a * b``), lists right under the sentence that introduces
them, indented display formulas; here and there reST roles and tables (``:func:``, ``====``).
Docutils reads ``|x|`` as a substitution, ``c_`` as a link, a lone ``*`` as the start of
emphasis, and a list or an indented line glued to a paragraph as an error. This extension
(hooked on ``autodoc-process-docstring``, which autosummary's summaries also go through)
makes the plain-text idioms mean what they mean in the terminal:

- ``\\``, ``|``, ``*`` (outside a ``*emphasis*`` or ``**strong**`` pair) and a ``_``
  closing a word are escaped, outside inline literals, roles and literal blocks (in a simple
  table, where an escape would shift the columns, ``|`` and ``*`` become look-alikes);
- a list glued to the sentence before it, an indented line glued to a paragraph and an
  unindent after such a block get the blank line reST needs;
- an indented block after a paragraph (a display formula) becomes a literal block, as it
  reads in the source; blocks under ``::``, directives, fields and list items are left alone.

Everything else is reST as written, and any other warning still fails ``make docs`` (-W).
"""

from __future__ import annotations

import re

#: spans that are not text: ``literal``, :role:`target`, `interpreted`
_CODE = re.compile(r"(``.+?``|:[\w:.-]+:`[^`]*`|`[^`]+`_{0,2})")
#: emphasis and strong pairs that docutils would accept
_STRONG_OR_EMPHASIS = re.compile(
    r"(?<![\w*\\])(\*\*(?=\S)[^*]*?(?<=\S)\*\*|\*(?=[^\s*])[^*]*?(?<=[^\s*])\*)(?![\w*])")
_BULLET = re.compile(r"(?:[-*+]|\d+[.)]|#\.)\s+(?=\S)")
_WORD_UNDERSCORE = re.compile(r"(?<=\w)_(?!\w)")
#: a border line of a simple table
_TABLE_BORDER = re.compile(r"^\s*=+( +=+)+\s*$")
#: in a table, where an escape would shift the columns: look-alike characters of equal width
_TABLE_CHARACTERS = str.maketrans({"|": "\u2223", "*": "\u2217"})


def _keep_emphasis(text: str, escape) -> str:
    """``escape`` applied to ``text`` outside its ``*emphasis*`` and ``**strong**`` pairs."""
    pieces = []
    last = 0
    for match in _STRONG_OR_EMPHASIS.finditer(text):
        pieces.append(escape(text[last:match.start()]))
        pieces.append(match.group(0))
        last = match.end()
    pieces.append(escape(text[last:]))
    return "".join(pieces)


def _escape_text(text: str) -> str:
    """Escape ``|``, stray ``*`` and word-closing ``_`` in a run of plain text."""
    return _keep_emphasis(text, _escape_plain)


def _escape_plain(text: str) -> str:
    text = text.replace("\\", "\\\\").replace("|", r"\|").replace("*", r"\*")
    return _WORD_UNDERSCORE.sub(r"\\_", text)


def escape_table_row(line: str) -> str:
    """A row of a simple table with ``|`` and stray ``*`` replaced by look-alikes."""
    parts = _CODE.split(line)
    return "".join(part if i % 2 else _keep_emphasis(part, lambda t: t.translate(
        _TABLE_CHARACTERS)) for i, part in enumerate(parts))


def escape_inline(line: str) -> str:
    """One line with its plain-text markup characters escaped, reST spans kept."""
    parts = _CODE.split(line)
    return "".join(part if i % 2 else _escape_text(part) for i, part in enumerate(parts))


def _indent(line: str) -> int:
    return len(line) - len(line.lstrip(" "))


def _starts_markup(text: str) -> bool:
    """A paragraph whose indented continuation is reST structure, not a display formula."""
    return (text.startswith((".. ", ":", "=")) or bool(_BULLET.match(text))
            or text.rstrip().endswith("::"))


def convert(lines: list[str]) -> list[str]:
    """The docstring's lines, made valid reST (see the module docstring)."""
    out: list[str] = []
    block = None  # the current block: (indent, first line stripped), None after a blank line
    column = 0  # where the current block's text runs (past a bullet)
    before = None  # the block before the last blank line: (indent, first line, last line)
    literal_base = None  # inside a literal block: the indentation it must exceed
    table = False  # inside a simple table

    def start_literal(base: int) -> None:
        nonlocal literal_base, block, before
        literal_base, block, before = base, None, None

    for line in lines:
        if table or (literal_base is None and _TABLE_BORDER.match(line)):
            # a simple table: rows kept as laid out; it ends at a blank line after a border
            table = not (not line.strip() and _TABLE_BORDER.match(out[-1] if out else ""))
            out.append(escape_table_row(line))
            block, before = None, None
            continue
        if not line.strip():
            if block is not None:
                before = (block[0], block[1], out[-1].strip())
            block = None
            out.append(line)
            continue
        indent = _indent(line)
        text = line.strip()
        if literal_base is not None:
            if indent > literal_base:
                out.append(line)
                continue
            literal_base = None
            if out[-1].strip():  # a literal block ends with a blank line
                out.append("")
        bullet = _BULLET.match(text)
        if block is None:
            if (before is not None and indent > before[0] and not _starts_markup(before[1])
                    and not before[2].endswith("::")):
                # an indented display under a plain paragraph: a literal block
                out.extend(["::", ""])
                start_literal(before[0])
                out.append(line)
                continue
        else:
            in_list = bool(_BULLET.match(block[1]))
            sibling = bullet and in_list and indent == block[0]
            if (bullet and not sibling and indent >= block[0]
                    and not out[-1].rstrip().endswith(":")):
                bullet = None  # a line that happens to start with "- " inside a paragraph
            if bullet and not sibling:
                out.append("")  # a list glued to the sentence that introduces it
                block = None
            elif indent > column and (in_list or not _starts_markup(block[1])):
                # a display glued to its paragraph: a literal block, as it reads in the source
                out.extend(["", " " * column + "::", ""])
                start_literal(column)
                out.append(line)
                continue
            elif indent < column and not sibling:
                out.append("")  # the end of an indented block or list item
                block = None
        if block is None:
            block = (indent, text)
            before = None
        if bullet and (block[0] == indent):
            column = indent + bullet.end()
        elif block[1] == text:
            column = indent
        if text.startswith(".. "):
            out.append(line)
            continue
        if text.endswith("::"):
            literal_base = indent
        start = indent + (bullet.end() if bullet else 0)  # a bullet stays a bullet
        out.append(line[:start] + escape_inline(line[start:]))
    return out


def process_docstring(app, what, name, obj, options, lines: list[str]) -> None:
    lines[:] = convert(lines)


def setup(app):
    app.setup_extension("sphinx.ext.autodoc")
    app.connect("autodoc-process-docstring", process_docstring)
    return {"parallel_read_safe": True, "parallel_write_safe": True}
