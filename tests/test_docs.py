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


def _layout_entries() -> dict[str, str]:
    """README's layout block as ``{first column: the entry's whole text}``; an entry is a line
    plus the continuation lines indented past its first column."""
    text = (REPO / "README.md").read_text(encoding="utf-8")
    block = text.split("## Layout", 1)[1].split("```", 2)[1]
    entries: dict[str, str] = {}
    key = None
    for line in block.splitlines():
        if not line.strip():
            continue
        indent = len(line) - len(line.lstrip())
        head = re.split(r"\s{2,}", line.strip(), maxsplit=1)[0]
        if indent <= 2 or key is None:
            key = ("  " if indent == 2 else "") + head
            entries[key] = line
        else:
            entries[key] += " " + line.strip()
    return entries


def _names(d: pathlib.Path) -> list[str]:
    out = [p.stem for p in d.glob("*.py") if p.stem != "__init__"]
    return sorted(out + [p.name for p in d.iterdir() if (p / "__init__.py").exists()])


def test_readme_layout_matches_the_tree():
    entries = _layout_entries()
    words = lambda s: set(re.findall(r"[A-Za-z_][A-Za-z0-9_]*", s))
    # Top-level modules of swiftjax: each is named first on some "  name" line (several per line).
    listed = {n for k in entries if k.startswith("  ") for n in re.split(r",\s*", k.strip().rstrip("/"))}
    tree = set(_names(REPO / "swiftjax"))
    assert listed == tree, f"README layout: missing {sorted(tree - listed)}, not in the tree {sorted(listed - tree)}"
    # Every package's modules appear in its entry.
    for pkg in sorted(p for p in (REPO / "swiftjax").iterdir() if (p / "__init__.py").exists()):
        missing = set(_names(pkg)) - words(entries[f"  {pkg.name}/"])
        assert not missing, f"README layout: swiftjax/{pkg.name}/ does not name {sorted(missing)}"
    missing = set(_names(REPO / "inference")) - words(entries["inference/"])
    assert not missing, f"README layout: inference/ does not name {sorted(missing)}"
    for top in ("swiftjax/", "inference/", "bench/", "tests/", "docs/", "notebooks/"):
        assert top in entries, f"README layout has no {top} entry"
