"""Numbers and tables as the book prints them: the same text on any computer.

A number a notebook prints may be compared, character for character, by notebook tests (nbval) on whatever
machine runs them. It must therefore say what the text around it claims and no more:

* :func:`num` prints a value that is zero up to rounding as zero, without a sign, and everything else to the
  digits asked for; values below a stated floor can be printed as ``< floor``;
* :func:`table` lays rows out as a :class:`Table`: a Markdown table in a notebook, aligned text in a terminal.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

__all__ = ["num", "table", "Table"]


def num(x, spec: str = ".2e", zero: float = 1e-12, floor: float | None = None) -> str:
    """Format one number for a page.

    * ``x``: the value (anything ``float()`` accepts); NaN and infinities print as such; None, a number a run did
      not measure (``row.get(key)``), prints as a dash, "–".
    * ``spec``: a format spec, e.g. ``".2e"``, ``".3f"``, ``"+.1e"``.
    * ``zero``: values with ``|x| < zero`` print as zero (rounding noise has no sign and no digits).
    * ``floor``: when given, values with ``|x| < floor`` (and not zero) print as ``< floor``, for quantities
      whose size below the floor depends on the computer (e.g. a residual at rounding level).
    """
    if x is None:
        return "–"
    x = float(x)
    if math.isfinite(x):
        if floor is not None and abs(x) < floor:
            return f"< {floor:.0e}".replace("e-0", "e-")
        if abs(x) < zero:
            x = 0.0
        x = x + 0.0  # -0.0 -> 0.0
    return format(x, spec)


class Table:
    """Rows under a header: Markdown in a notebook (on the site, a table that scrolls in its own box), aligned
    plain text elsewhere. Arguments as in :func:`table`."""

    def __init__(self, header: Sequence[str], rows: Sequence[Sequence], align: str | None = None):
        self.header = [str(h) for h in header]
        self.rows = [[str(c) for c in row] for row in rows]
        if any(len(r) != len(self.header) for r in self.rows):
            raise ValueError(f"every row needs {len(self.header)} cells (one per column of the header)")
        self.align = align or "l" + "r" * (len(self.header) - 1)
        if len(self.align) != len(self.header) or set(self.align) - set("lcr"):
            raise ValueError(f"align must be one of l, c, r per column; got {self.align!r}")

    def _repr_markdown_(self) -> str:
        esc = lambda s: s.replace("|", "\\|")  # noqa: E731
        rule = {"l": ":--", "c": ":-:", "r": "--:"}
        lines = [
            "| " + " | ".join(esc(h) for h in self.header) + " |",
            "|" + "|".join(rule[a] for a in self.align) + "|",
        ]
        lines += ["| " + " | ".join(esc(c) for c in row) + " |" for row in self.rows]
        return "\n".join(lines)

    def __str__(self) -> str:
        cols = list(zip(self.header, *self.rows))
        widths = [max(len(c) for c in col) for col in cols]
        pad = {"l": str.ljust, "c": str.center, "r": str.rjust}

        def line(cells):
            return "  ".join(pad[a](c, w) for c, w, a in zip(cells, widths, self.align)).rstrip()

        return "\n".join([line(self.header), line(["-" * w for w in widths])] + [line(r) for r in self.rows])

    __repr__ = __str__


def table(header: Sequence[str], rows: Sequence[Sequence], align: str | None = None) -> Table:
    """A :class:`Table` of ``rows`` (sequences of already formatted cells) under ``header``.

    * ``header``: the column titles (Markdown, so ``$...$`` math renders on the site).
    * ``rows``: one sequence of cells per row, as strings (format numbers with :func:`num`).
    * ``align``: one letter per column, ``l``, ``c`` or ``r``; default: first left, the rest right.
    """
    return Table(header, rows, align)
