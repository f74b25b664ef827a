"""Names a user hands the tools (an agent's or run's name in a scores file, a run's recorded algorithm),
written once for every table, page and figure (torch-free).

- ``check_name``: whether text can stand as a name at all (not blank, printable, at most ``NAME_LENGTH``).
- ``key``: the one normalisation of names that must not collide: two names with one key look the same to a
  reader (Unicode compatibility forms, case, spacing, invisible characters, and Latin lookalikes from the
  Cyrillic and Greek scripts: ``rеference`` with a Cyrillic ``е`` is ``reference``). A name that takes
  another's key, a reserved one's above all, is refused (``collision``).
- ``markdown_cell``: a name as one cell of a Markdown table, shown as written (no column, link, image,
  format or maths of its own).
- ``csv_cell`` / ``csv_name``: a name as a CSV cell no spreadsheet runs as a formula (a leading ``=``,
  ``+``, ``-``, ``@``, tab or carriage return gets a ``'`` before it), and back.
- ``figure_label``: a name as matplotlib draws it as written (no mathtext).
"""

from __future__ import annotations

import re
import unicodedata

NAME_LENGTH = 200  # an agent's or a run's name: longer is not a name

# Letters of other scripts that a reader takes for Latin ones (Unicode's confusables for the Cyrillic and Greek
# letters that look like a Latin letter in common fonts), after NFKC and casefolding.
LOOKALIKES = str.maketrans({
    "а": "a", "в": "b", "с": "c", "ԁ": "d", "е": "e", "һ": "h", "і": "i", "ј": "j", "к": "k", "ӏ": "l", "м": "m",
    "н": "h", "о": "o", "р": "p", "ԛ": "q", "г": "r", "ѕ": "s", "т": "t", "ц": "u", "ѵ": "v", "ԝ": "w", "х": "x",
    "у": "y", "ё": "e", "ї": "i", "ү": "y", "ғ": "f",
    "α": "a", "β": "b", "ε": "e", "η": "n", "ι": "i", "κ": "k", "ν": "v", "ο": "o", "ρ": "p", "τ": "t", "υ": "u",
    "χ": "x", "γ": "y", "ϲ": "c", "ϳ": "j", "ω": "w", "μ": "u", "ς": "c", "σ": "o",
})
FORMULA_START = ("=", "+", "-", "@", "\t", "\r")
MARKDOWN = set("\\`*_[]!|$~")  # what Markdown (and GitHub's maths) reads as markup inside a table cell


def check_name(text, what: str) -> str | None:
    """Why ``text`` cannot stand as a ``what``'s name in a table (None: it can): not text, empty or blank,
    control or invisible characters (a line break splits a table's row; a zero-width space hides a
    difference), or more than ``NAME_LENGTH`` characters."""
    if not isinstance(text, str) or not text.strip():
        return f"the {what} name is empty"
    if len(text) > NAME_LENGTH:
        return f"the {what} name is {len(text):,} characters long; a name is at most {NAME_LENGTH}"
    if not text.isprintable() or any(unicodedata.category(c) == "Cf" for c in text):
        return f"the {what} name {text[:60]!r} holds control characters (or invisible ones); a name is printable text"
    return None


_NAMED = {"ALPHA": "a", "SCRIPT G": "g", "DOTLESS I": "i", "DOTLESS J": "j", "LONG S": "s", "IOTA": "i",
          "OPEN O": "o", "TURNED A": "a", "SCRIPT A": "a", "SMALL CAPITAL": ""}


def _latin(c: str) -> str:
    """The Latin letter a character of a Latin-like name shows (``ʀ``, LATIN LETTER SMALL CAPITAL R: ``r``), or the
    character itself."""
    if c.isascii():
        return c
    name = unicodedata.name(c, "")
    letter = re.search(r"(?:SMALL CAPITAL|CAPITAL LETTER|SMALL LETTER|LETTER) ([A-Z])(?: |$)", name)
    if letter:
        return letter.group(1).lower()
    return next((latin for word, latin in _NAMED.items() if word and word in name), c)


def key(text: str) -> str:
    """What a reader sees of ``text``, as one string: NFKC, casefolded, lookalike letters as the Latin ones (other
    scripts' by ``LOOKALIKES``, Latin variants by their Unicode names), and only letters and digits kept (spaces,
    punctuation, symbols, marks and invisible characters dropped: ``reference˸ oracle`` is ``reference: oracle``).
    Two names with one key are one name to a reader."""
    folded = unicodedata.normalize("NFKC", text).casefold().translate(LOOKALIKES)
    decomposed = unicodedata.normalize("NFKD", folded)
    return "".join(_latin(c) for c in decomposed if c.isalnum()).casefold()


def collision(names, reserved=(), reserved_start: str | None = None) -> str | None:
    """Why the distinct ``names`` cannot stand side by side (None: they can): one looks like another (the same
    ``key``), or like a ``reserved`` name it is not, or begins as ``reserved_start`` does (by key) without being
    a reserved name."""
    seen: dict[str, str] = {key(name): name for name in reserved}
    kept = set(reserved)
    for name in names:
        if name in kept:
            continue
        if reserved_start is not None and key(name).startswith(key(reserved_start)):
            return (f"the name {name!r} begins as the board's own {reserved_start!r} names do; give it a name "
                    "of its own")
        other = seen.get(key(name))
        if other is not None:
            owner = "a reserved name" if other in reserved else "another name"
            return f"the name {name!r} looks like {owner}, {other!r}; give it a name of its own"
        seen[key(name)] = name
        kept.add(name)
    return None


def markdown_cell(text: str) -> str:
    """``text`` as one cell of a Markdown table, shown as written: every character Markdown may read as
    markup escaped with a backslash, ``<`` and ``&`` as entities, control characters (a line break ends a
    table's row) as their escapes, and the starts of links GitHub makes of bare text (``://``, ``www.``)
    broken by an entity, so that a name cannot add a row, column, link, embed, format or typeset anything."""
    text = "".join(c.encode("unicode_escape").decode() if unicodedata.category(c)[0] == "C" else c
                   for c in str(text))
    text = text.replace("&", "&amp;").replace("<", "&lt;")
    text = re.sub(r"(?i)(www)\.", r"\1&#46;", text.replace("://", "&#58;//"))
    return "".join("\\" + c if c in MARKDOWN else c for c in text)


def csv_cell(value):
    """A CSV cell no spreadsheet runs as a formula: text starting as a formula does (after any ``'``) gets a ``'``
    first (``csv_name`` takes it off, so that every name reads back as written); numbers (a negative one too) and
    other values are as they are."""
    return "'" + value if isinstance(value, str) and _formula(value) else value


def csv_name(text: str) -> str:
    """A name as ``csv_cell`` wrote it, as it was."""
    return text[1:] if text.startswith("'") and _formula(text[1:]) else text


def _formula(text: str) -> bool:
    if not text.lstrip("'").startswith(FORMULA_START):
        return False
    try:
        float(text)
    except ValueError:
        return True
    return text.strip() != text


def figure_label(text: str) -> str:
    """``text`` as a figure (title, legend, tick) shows it verbatim: matplotlib reads ``$...$`` as mathematics (an
    ill-formed one fails the drawing) and hides legend labels that start with an underscore."""
    text = str(text).replace("$", r"\$")
    return " " + text if text.startswith("_") else text
