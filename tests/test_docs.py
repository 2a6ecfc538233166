"""The documentation's sources stay consistent without building the site.

``mkdocs build --strict`` (CI, after the tests) is the full check; this catches, in the test
suite that everyone runs, a README section that a docs page includes by marker
(``--8<-- "README.md:name"``, markers ``<!-- --8<-- [start:name] -->`` / ``[end:name]``) and
that lost a marker in an edit, and runs the code blocks of the docs pages that are marked
``<!-- test: run -->`` (examples that claim to run as they are).
"""

from __future__ import annotations

import pathlib
import re

REPO = pathlib.Path(__file__).resolve().parents[1]
SNIPPET = re.compile(r'^--8<-- "([^":]+):([^"]+)"\s*$', re.MULTILINE)


def _markers(text: str, name: str, kind: str) -> list[int]:
    return [m.start() for m in re.finditer(re.escape(f"<!-- --8<-- [{kind}:{name}] -->"), text)]


def test_every_included_section_has_one_start_and_one_end_marker():
    refs = []
    for page in sorted((REPO / "docs").rglob("*.md")):
        refs += [(page.relative_to(REPO), f, n) for f, n in SNIPPET.findall(page.read_text(encoding="utf-8"))]
    assert refs, "no docs page includes a README section"
    for page, file, name in refs:
        text = (REPO / file).read_text(encoding="utf-8")
        start, end = _markers(text, name, "start"), _markers(text, name, "end")
        assert len(start) == 1 and len(end) == 1 and start[0] < end[0], (
            f"{page} includes {file}:{name}, which needs exactly one start and one end marker "
            f"(found {len(start)} start, {len(end)} end)"
        )


RUNNABLE = re.compile(r"<!-- test: run -->\s*```python\n(.*?)```", re.DOTALL)


def test_marked_examples_run():
    blocks = []
    for page in sorted((REPO / "docs").rglob("*.md")):
        blocks += [(page.name, code) for code in RUNNABLE.findall(page.read_text(encoding="utf-8"))]
    assert blocks, "no docs page marks an example as runnable"
    for name, code in blocks:
        exec(compile(code, f"<{name} example>", "exec"), {"__name__": "__docs_example__"})
