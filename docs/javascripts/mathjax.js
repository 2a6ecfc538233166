// MathJax 3 configuration; the renderer (tex-svg.js, self-contained SVG output: no web fonts)
// is served by the site itself (docs/hooks.py copies it in), so the maths renders offline.
// Pages: pymdownx.arithmatex's spans and divs (\( \) and \[ \]); notebooks: their markdown
// cells ($ $ and $$ $$).  Nothing else on a page is scanned.
window.MathJax = {
  tex: {
    inlineMath: [["\\(", "\\)"], ["$", "$"]],
    displayMath: [["\\[", "\\]"], ["$$", "$$"]],
    processEscapes: true,
    processEnvironments: true,
  },
  svg: { fontCache: "global" },
  // A classed element is skipped with its subtree, unless its class is one of the two above
  // (".+": an unclassed <p> inside a notebook cell inherits its cell's verdict).
  options: { ignoreHtmlClass: ".+", processHtmlClass: "arithmatex|jp-MarkdownOutput" },
};
document$.subscribe(() => { MathJax.typesetPromise && MathJax.typesetPromise(); });
