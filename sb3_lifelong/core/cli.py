"""
The command lines' help in plain text. The module docstrings that describe the package's commands are
reStructuredText, written for the docs; :func:`plain_text` turns one into what ``--help`` prints in a terminal.
"""

import re
import textwrap

__all__ = ["plain_text"]

#: a role, ``:mod:`x```, ``:class:`~a.b.C```, ``:py:func:`f```, ``:doc:`title <path>```: a ``~`` (group 1), the
#: name or title (group 2), the target after an explicit title (group 3)
ROLE = re.compile(r":(?:[a-z]+:)?[a-z]+:`(~?)([^`<]*?)\s*(?:<([^>`]*)>)?`")
#: a hyperlink, ```text <url>`_``, and interpreted text, ```text```
LINK = re.compile(r"`([^`<]+?)\s*<([^>`]+)>`__?")
INTERPRETED = re.compile(r"(?<![`\w])`([^`]+)`(?![`\w])")
#: an inline literal, ````text````, and strong emphasis, ``**text**``
LITERAL = re.compile(r"``([^`]+?)``")
STRONG = re.compile(r"\*\*([^*]+?)\*\*")


def _role(match: "re.Match[str]") -> str:
    """:return: what a reader of the docs sees of a role: its title, or its name (the last part of it after ``~``)"""
    shorten, name, target = match.groups()
    if target is not None and name:  # :doc:`title <path>`: the title
        return name
    if target is not None:  # :ref:`<label>`, with no title
        name = target
    return name.rsplit(".", 1)[-1] if shorten else name


def plain_text(text: str) -> str:
    """
    A reStructuredText docstring as plain text for a terminal: roles (``:mod:``, ``:class:``, ...), inline literals
    (double backticks), interpreted text and ``**strong**`` lose their markup, a hyperlink becomes ``text (url)``,
    and a paragraph's literal-block marker ``::`` becomes ``:`` (the indented block after it stays as it is).

    :param text: the docstring (indented or not)
    :return: the same text, dedented and stripped, without reStructuredText markup
    """
    text = textwrap.dedent(text).strip("\n")
    text = ROLE.sub(_role, text)
    text = LINK.sub(r"\1 (\2)", text)
    text = LITERAL.sub(r"\1", text)
    text = INTERPRETED.sub(r"\1", text)
    text = STRONG.sub(r"\1", text)
    lines = []
    for line in text.split("\n"):
        if line.strip() == "::":  # an expanded literal-block marker, alone on its line
            continue
        if line.endswith("::"):
            # "Usage::" -> "Usage:"; "a paragraph ::" -> "a paragraph"
            line = line[:-3].rstrip() if line.endswith(" ::") else line[:-1]
        lines.append(line)
    return re.sub(r"\n{3,}", "\n\n", "\n".join(lines)).strip()  # no two blank lines where a marker was
