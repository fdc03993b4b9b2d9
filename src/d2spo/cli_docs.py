"""The ``d2spo docs`` command (``cli.commands`` lists it): the pages of docs/, which ship with the
package (``d2spo/docs`` is the repository's docs/), read in the terminal, so that a help text or an
error naming "docs/env.md" can be followed where d2spo is installed."""

from __future__ import annotations

import dataclasses
from importlib import resources
from pathlib import Path

import tyro
from rich.console import Console
from rich.markdown import Markdown

from d2spo.errors import UserError


def pages() -> dict[str, Path]:
    """Page name (``env`` for docs/env.md) -> its file, in the installed package."""
    root = Path(str(resources.files("d2spo") / "docs"))
    return {p.stem: p for p in sorted(root.glob("*.md"))} if root.is_dir() else {}


def title(page: Path) -> str:
    """The page's first heading, without its #s."""
    for line in page.read_text(encoding="utf-8").splitlines():
        if line.startswith("#"):
            return line.lstrip("#").strip()
    return ""


@dataclasses.dataclass
class DocsCmd:
    """Read a page of d2spo's documentation (docs/NAME.md) in the terminal; without NAME, list the pages."""

    page: tyro.conf.Positional[str | None] = None
    """The page: its name (env), or as help texts name it (docs/env.md)."""
    path: bool = False
    """Print the page's file path instead of the page."""

    def run(self) -> int:
        found = pages()
        if not found:
            raise UserError("the documentation is not installed with this copy of d2spo (no d2spo/docs)")
        if self.page is None:
            width = max(map(len, found))
            for name, p in found.items():
                print(f"{name.ljust(width)}  {title(p)}")
            print("\nd2spo docs NAME shows one (--path: where it is)")
            return 0
        name = Path(self.page).stem
        if name not in found:
            raise UserError(f"no documentation page {self.page!r}; the pages: {', '.join(found)}")
        if self.path:
            print(found[name])
            return 0
        Console().print(Markdown(found[name].read_text(encoding="utf-8")))
        return 0
