"""Report pages as data, rendered to Markdown and HTML by the same Jinja2 templates.

A page is a title, one headline line and sections; a section holds lines of text, tables and
pictures. The report (`report.py`) and the comparison of two runs (`compare.py`) build pages; the
templates in `templates/` decide how they look, so both formats always show the same values and
marks. The HTML page is one file with its pictures beside it (relative links): it opens offline.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from jinja2 import Environment, PackageLoader, StrictUndefined, select_autoescape

MARKS = ("best", "second", "better", "worse", "")


@dataclass
class Cell:
    """One table cell: its text as shown and how it is marked."""

    text: str
    mark: str = ""  # best | second (per column) | better | worse (comparisons) | ""

    def __post_init__(self) -> None:
        if self.mark not in MARKS:
            raise ValueError(f"cell {self.text!r}: mark {self.mark!r}; expected one of {MARKS}")

    @property
    def numeric(self) -> bool:
        """A number as shown (`12.34`, `+0.50`, `2.96×`, `n/a`): right-aligned on the page."""
        try:
            float(self.text.rstrip("×"))
        except ValueError:
            return self.text == "n/a"
        return True


@dataclass
class Table:
    header: list[str]
    rows: list[list[Cell]]
    note: str = ""


@dataclass
class Section:
    title: str
    lines: list[str] = field(default_factory=list)
    tables: list[Table] = field(default_factory=list)
    images: list[tuple[str, str]] = field(default_factory=list)  # (file beside the page, caption)


@dataclass
class Page:
    title: str
    headline: str
    sections: list[Section]


def text_cells(*texts: object) -> list[Cell]:
    """Unmarked cells from plain values."""
    return [Cell(str(t)) for t in texts]


_ENVIRONMENT = Environment(
    loader=PackageLoader("umad_common.viz", "templates"),
    autoescape=select_autoescape(enabled_extensions=("html.j2",), default_for_string=False),
    undefined=StrictUndefined,
    trim_blocks=True,
    lstrip_blocks=True,
    keep_trailing_newline=True,
)


def render_table_markdown(table: Table) -> str:
    """One table as Markdown (the table files beside the report: table.md, per_scenario.md, ...)."""
    return _ENVIRONMENT.get_template("table.md.j2").render(table=table)


def render_page(page: Page, form: str) -> str:
    """The page as `md` or `html` text."""
    return _ENVIRONMENT.get_template(f"page.{form}.j2").render(page=page)


def write_page(page: Page, out: Path, stem: str) -> tuple[Path, Path]:
    """Write `stem.md` and `stem.html` into `out`; returns their paths."""
    paths = out / f"{stem}.md", out / f"{stem}.html"
    for path, form in zip(paths, ("md", "html"), strict=True):
        path.write_text(render_page(page, form))
    return paths
