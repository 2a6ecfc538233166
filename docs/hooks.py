"""MkDocs hooks: the API reference is generated from the source tree, and the benchmark pages
are whatever ``docs/performance/*.md`` holds.

The API pages are read by griffe's static analysis (nothing imported); the options page imports
the option schema.

* ``api/<module>.md`` for every public module and package of ``swiftjax`` and ``inference``
  (names starting with ``_`` are private and skipped, and so is a module whose docstring
  starts with "Deprecated": a moved module's alias, named on the index page); a package's page documents the
  package and then each of its public submodules, so a module split into a package keeps
  one page and needs no edit here.  ``api/index.md`` lists them with their one-line summaries.
* ``options.md``: every method option of ``PipelineConfig`` (flag, TOML key, default, what it
  accepts, what it does), from the option schema itself.  This imports
  ``swiftjax.pipeline.config`` (JAX, never torch: the hook fails the build if torch was pulled in).
* ``commands.md``: each ``swiftjax`` subcommand's ``--help``, from the CLI's own parser.
* The "Benchmarks" section lists ``performance/index.md``, then the pages in
  ``PERFORMANCE_ORDER`` that exist, then any other page found there (alphabetical).
* The maths renders offline: MathJax 3 (its SVG output, ``tex-svg.js``, and the TeX
  extensions it may autoload) is copied into the site under ``javascripts/mathjax/`` from
  the installed Python package that ships it (PyPI ``django-static-mathjax``: MathJax's
  files, nothing of Django is imported); nothing is fetched from a CDN.
"""

from __future__ import annotations

import ast
import dataclasses
import pathlib
import re
import sys

from mkdocs.structure.files import File

ROOT = pathlib.Path(__file__).resolve().parents[1]
PACKAGES = ("swiftjax", "inference")
PERFORMANCE_ORDER = ("sim3", "align", "loops", "posegraph", "coldstart", "pipeline", "io", "synthetic", "inference")

_pages: dict[str, str] = {}


_ROLE = re.compile(r":(?:py:)?[a-z]+:`~?([^`]+)`")


def _summary(path: pathlib.Path) -> str:
    """The first line of a module's docstring, its reST roles as inline code."""
    doc = ast.get_docstring(ast.parse(path.read_text(encoding="utf-8"))) or ""
    return _ROLE.sub(r"`\1`", doc.strip().splitlines()[0]) if doc.strip() else ""


def _public(name: str) -> bool:
    return not name.startswith("_")


def _modules(package_dir: pathlib.Path, dotted: str) -> list[tuple[str, pathlib.Path, bool]]:
    """(dotted name, file, is_package) of the public direct children of a package, sorted."""
    out = []
    for child in sorted(package_dir.iterdir()):
        if child.is_dir() and (child / "__init__.py").exists() and _public(child.name):
            out.append((f"{dotted}.{child.name}", child / "__init__.py", True))
        elif child.suffix == ".py" and child.stem != "__init__" and _public(child.stem):
            out.append((f"{dotted}.{child.stem}", child, False))
    return out


def _package_page(dotted: str, init: pathlib.Path) -> str:
    lines = [
        f"# `{dotted}`",
        "",
        f"::: {dotted}",
        "    options:",
        "      members: false",
        "      show_root_heading: false",
        "",
    ]
    for sub, path, is_pkg in _modules(init.parent, dotted):
        if is_pkg:  # a nested package: its docstring and its modules, one level deeper
            lines += [f"::: {sub}", "    options:", "      members: false", ""]
            for sub2, _, _ in _modules(path.parent, sub):
                lines += [f"::: {sub2}", "    options:", "      heading_level: 3", ""]
        else:
            lines += [f"::: {sub}", ""]
    return "\n".join(lines)


def _module_page(dotted: str) -> str:
    return f"# `{dotted}`\n\n::: {dotted}\n    options:\n      show_root_heading: false\n"


def _api() -> tuple[dict[str, str], list]:
    pages: dict[str, str] = {}
    nav: list = [{"Overview": "api/index.md"}]
    rows = ["# API reference", "", "Generated from the docstrings (static analysis: nothing is imported).", ""]
    for package in PACKAGES:
        pdir = ROOT / package
        section: list = []
        rows += [f"## `{package}`", "", f"{_summary(pdir / '__init__.py')}", "", "| module | what |", "| --- | --- |"]
        entries = [(package, pdir / "__init__.py", True)] if package == "inference" else _modules(pdir, package)
        deprecated = []
        for dotted, path, is_pkg in entries:
            if _summary(path).startswith("Deprecated"):  # a moved module's alias: no page
                deprecated.append(f"`{dotted}` ({_summary(path)[len('Deprecated') :].lstrip(': ')})")
                continue
            uri = f"api/{dotted}.md"
            pages[uri] = _package_page(dotted, path) if is_pkg else _module_page(dotted)
            section.append({dotted: uri})
            summary = _summary(path).replace("|", "\\|")
            rows.append(f"| [`{dotted}`]({dotted}.md) | {summary} |")
        rows.append("")
        if deprecated:
            rows += ["Deprecated aliases, kept for one release: " + "; ".join(deprecated) + ".", ""]
        nav.append({package: section})
    pages["api/index.md"] = "\n".join(rows)
    return pages, nav


def _options_page() -> str:
    sys.path.insert(0, str(ROOT))
    try:
        from swiftjax import options
        from swiftjax.pipeline.config import PipelineConfig
    finally:
        sys.path.pop(0)
    if "torch" in sys.modules:
        raise RuntimeError("importing swiftjax's option schema imported torch: swiftjax must never import it")
    fields = {f.name: f for f in dataclasses.fields(PipelineConfig)}
    specs = options.specs(PipelineConfig)
    lines = [
        "# Options",
        "",
        "Every method parameter is an option of `swiftjax.pipeline.PipelineConfig`, with the paper's",
        "(or the authors' code's) default. The same declaration gives the Python field, the",
        "command-line flag of `swiftjax reconstruct` and `swiftjax demo`, and the key of a",
        "`--config file.toml`; values are checked against it before any work (`swiftjax.options`).",
        "An option's *stage* is the first stage of a run whose stored result it changes: a",
        "resumed run redoes that stage and the ones after it.",
        "",
        "This page is generated from the schema when the documentation is built.",
        "",
    ]
    for stage in options.STAGES:
        names = [n for n, sp in specs.items() if sp.stage == stage]
        if not names:
            continue
        lines += [
            f"## Stage `{stage}`",
            "",
            "| option (TOML key) | flag | default | accepts | what |",
            "| --- | --- | --- | --- | --- |",
        ]
        for n in names:
            sp, default = specs[n], fields[n].default
            flag = options.flag(n)
            if sp.kind is bool:
                flag = f"{flag}, --no-{flag[2:]}"
            shown = "none" if default is None else str(default).lower() if isinstance(default, bool) else str(default)
            cells = [f"`{n}`", f"`{flag}`", f"`{shown}`", sp.allowed(n), sp.help]
            lines.append("| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |")
        lines.append("")
    return "\n".join(lines)


def _commands_page() -> str:
    import argparse
    import os

    sys.path.insert(0, str(ROOT))
    try:
        from swiftjax import cli
    finally:
        sys.path.pop(0)
    if "torch" in sys.modules:
        raise RuntimeError("importing swiftjax.cli imported torch: swiftjax must never import it")
    columns = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = "100"  # argparse wraps to the terminal width; a fixed width here
    try:
        parser = cli.build_parser()
        sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        lines = [
            "# Command reference",
            "",
            "`swiftjax --help` and each subcommand's `--help`, generated from the CLI's own parser when",
            "the documentation is built. The method options of `reconstruct` and `demo` are explained,",
            "by stage, on [Options](options.md); the commands in context on [CLI and outputs](cli.md).",
            "",
            "```text",
            parser.format_help().rstrip(),
            "```",
            "",
        ]
        for name, p in sub.choices.items():
            lines += [f"## `swiftjax {name}`", "", "```text", p.format_help().rstrip(), "```", ""]
    finally:
        if columns is None:
            os.environ.pop("COLUMNS", None)
        else:
            os.environ["COLUMNS"] = columns
    return "\n".join(lines)


def _performance_nav(docs_dir: pathlib.Path) -> list:
    perf = docs_dir / "performance"
    found = {p.stem for p in perf.glob("*.md")} - {"index"}
    ordered = [s for s in PERFORMANCE_ORDER if s in found] + sorted(found - set(PERFORMANCE_ORDER))
    return [{"Overview": "performance/index.md"}] + [f"performance/{s}.md" for s in ordered]


def _replace(nav: list, title: str, entries: list) -> None:
    for item in nav:
        if isinstance(item, dict) and title in item:
            item[title] = entries
            return
    nav.append({title: entries})


def on_config(config):
    global _pages
    _pages, api_nav = _api()
    _pages["options.md"] = _options_page()
    _pages["commands.md"] = _commands_page()
    _replace(config["nav"], "API reference", api_nav)
    _replace(config["nav"], "Benchmarks", _performance_nav(pathlib.Path(config["docs_dir"])))
    return config


MATHJAX_URI = "javascripts/mathjax"


def _mathjax_dir() -> pathlib.Path:
    """MathJax 3's ``es5`` folder from the installed ``django-static-mathjax`` package."""
    import importlib.util

    spec = importlib.util.find_spec("mathjax")
    roots = list(spec.submodule_search_locations or []) if spec else []
    es5 = pathlib.Path(roots[0]) / "static" / "mathjax" / "es5" if roots else None
    if es5 is None or not (es5 / "tex-svg.js").is_file():
        raise RuntimeError(
            "MathJax is not installed: pip install -c constraints.txt -e '.[docs]' "
            "(django-static-mathjax ships MathJax 3's files)"
        )
    return es5


def on_files(files, config):
    for uri, text in _pages.items():
        files.append(File.generated(config, uri, content=text))
    es5 = _mathjax_dir()
    for path in [es5 / "tex-svg.js", *sorted((es5 / "input" / "tex" / "extensions").rglob("*.js"))]:
        uri = f"{MATHJAX_URI}/{path.relative_to(es5).as_posix()}"
        files.append(File.generated(config, uri, abs_src_path=str(path)))
    return files
