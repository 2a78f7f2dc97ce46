"""The contrast of text as the browser renders it, checked with axe-core (issue 33.10).

``tests/app/test_contrast.py`` checks the colour pairs the stylesheet declares; this checks what a
page shows: axe-core's ``color-contrast`` rule (Deque's engine, the WCAG 2.1 AA check: 4.5:1,
3:1 for large text, i.e. 24 px, or 18.66 px bold) takes every visible text element, its computed
colour and the background it is drawn on (the first opaque background behind it, layers and
opacity included), and reports each one below the ratio. Elements whose background it cannot know
(text over a picture or a gradient, or in an SVG: the report's charts, whose white-on-grade
pairs tests/app/test_contrast.py checks) come back as ``incomplete``, with axe's reason, apart.

axe-core is pinned in the repository's ``package.json`` and installed with ``npm ci`` (.ci/run
does it); it is injected into the page from ``node_modules/axe-core/axe.min.js``, so it runs
offline. The pages' Content-Security-Policy refuses injected scripts, so the browser context that
audits must be made with ``bypass_csp=True``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

REPO_ROOT = Path(__file__).resolve().parents[1]
AXE_JS = REPO_ROOT / "node_modules" / "axe-core" / "axe.min.js"
AXE_MISSING = f"axe-core is not installed ({AXE_JS} is missing): run `npm ci` in {REPO_ROOT}"

# axe.run limited to the contrast rule; each violating node with its numbers.
_RUN_AXE = """async () => {
  const result = await axe.run(document, {runOnly: {type: 'rule', values: ['color-contrast']}});
  const nodes = (kind) => result[kind].flatMap(rule => rule.nodes.map(node => {
    const data = (node.any[0] || {}).data || {};
    return {selector: node.target.join(' '), html: node.html.slice(0, 160), ratio: data.contrastRatio || null,
            expected: data.expectedContrastRatio || null, colour: data.fgColor || null, background: data.bgColor || null,
            font: [data.fontSize, data.fontWeight].filter(Boolean).join(' ')};
  }));
  const undecided = result.incomplete.flatMap(rule => rule.nodes.map(node =>
    ({selector: node.target.join(' '), why: node.any.map(check => check.message).join('; ')})));
  return {violations: nodes('violations'), incomplete: undecided, version: axe.version};
}"""


def axe_installed() -> bool:
    return AXE_JS.is_file()


def audit_contrast(page: Any) -> dict[str, Any]:
    """axe-core's colour-contrast check of ``page`` as it is now: ``violations`` (selector, html,
    ratio, expected ratio, colours, font), the ``incomplete`` elements (selector, why axe could
    not decide) and axe's ``version``. The page's context must bypass the CSP (``bypass_csp=True``)."""
    if not axe_installed():
        raise FileNotFoundError(AXE_MISSING)
    if not page.evaluate("() => typeof window.axe !== 'undefined'"):
        page.add_script_tag(path=str(AXE_JS))
    result: dict[str, Any] = page.evaluate(_RUN_AXE)
    return result


def describe(violation: dict[str, Any]) -> str:
    """One line for a contrast violation: where, how much, which colours."""
    return (
        f"{violation['selector']}: {violation['ratio']}:1 < {violation['expected']} "
        f"({violation['colour']} on {violation['background']}, {violation['font']}) {violation['html']}"
    )
