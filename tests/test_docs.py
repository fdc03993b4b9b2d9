"""Every ```python block of README.md and docs/*.md runs as it is written (issue #35): a reader pastes
a page's blocks in order into one interpreter. Blocks that show signatures rather than code are
fenced as ```text. Each page runs in a fresh namespace, in a temporary working directory."""

from __future__ import annotations

import re
from pathlib import Path

import matplotlib
import pytest

ROOT = Path(__file__).resolve().parent.parent
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
BLOCK = re.compile(r"^```python\n(.*?)^```", re.S | re.M)


def blocks(page: Path) -> list[str]:
    return BLOCK.findall(page.read_text())


@pytest.mark.parametrize("page", [p for p in PAGES if blocks(p)], ids=lambda p: p.name)
def test_every_python_block_runs_as_written(page, tmp_path, monkeypatch, capsys):
    matplotlib.use("Agg")
    monkeypatch.chdir(tmp_path)
    namespace: dict = {"__name__": "__main__"}
    for i, code in enumerate(blocks(page), 1):
        try:
            exec(compile(code, f"{page.name}, python block {i}", "exec"), namespace)
        except Exception as e:  # noqa: BLE001 - the test names the block that failed
            pytest.fail(f"{page.name}, python block {i} of {len(blocks(page))}: {type(e).__name__}: {e}")


def test_the_pages_ship_with_the_package_and_d2spo_docs_reads_them(capsys):
    from d2spo.cli import main
    from d2spo.cli_docs import pages

    shipped = pages()
    assert set(shipped) == {p.stem for p in (ROOT / "docs").glob("*.md")}
    assert main(["docs"]) == 0
    listing = capsys.readouterr().out
    assert "ltl  " in listing and "LTL tasks" in listing
    assert main(["docs", "docs/ltl.md"]) == 0 and "Büchi automata" in capsys.readouterr().out
    assert main(["docs", "ltl", "--path"]) == 0 and capsys.readouterr().out.strip().endswith("ltl.md")
    assert main(["docs", "nope"]) == 2
    assert capsys.readouterr().err.strip().splitlines() == [
        f"d2spo: error: no documentation page 'nope'; the pages: {', '.join(shipped)}"]


def test_every_page_the_code_names_exists():
    """Help texts and errors name pages as docs/NAME.md: `d2spo docs NAME` must find each."""
    named = set()
    for path in (ROOT / "src" / "d2spo").rglob("*.py"):
        named |= set(re.findall(r"docs/([a-z_]+)\.md", path.read_text(encoding="utf-8")))
    assert named and named <= {p.stem for p in (ROOT / "docs").glob("*.md")}, named
