"""Every relative link in the README and docs/ resolves: the file exists and, for a Markdown file,
the ``#anchor`` is one of its headings as GitHub slugs them.

GitHub's rule: the heading's rendered text, lower-cased, every character that is not a letter,
mark, decimal or letter number, connector punctuation (``_``), hyphen or space removed, each
space a hyphen; a repeated slug gets ``-1``, ``-2``… in document order.
"""
from __future__ import annotations

import re
import unicodedata
from pathlib import Path
from urllib.parse import unquote

import pytest

REPO = Path(__file__).resolve().parents[1]

_FENCE = re.compile(r"^\s*(`{3,}|~{3,})")
_HEADING = re.compile(r"^ {0,3}(#{1,6})\s+(.*?)(?:\s+#+)?\s*$")
_CODE_SPAN = re.compile(r"(`+)(.+?)\1")
_LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]*)>?(?:\s+\"[^\"]*\")?\s*\)")
_HTML_ID = re.compile(r"<a\s+(?:name|id)=\"([^\"]+)\"")
_KEPT = ("Nd", "Nl", "Pc")


def pages() -> list[Path]:
    """The README, the other top-level pages and every page under docs/."""
    return sorted(REPO.glob("*.md")) + sorted((REPO / "docs").rglob("*.md"))


def _prose_lines(text: str) -> list[tuple[int, str]]:
    """(line number, line) outside fenced code blocks."""
    out, fence = [], None
    for n, line in enumerate(text.splitlines(), 1):
        m = _FENCE.match(line)
        if m:
            mark = m.group(1)
            if fence is None:
                fence = mark
            elif mark[0] == fence[0] and len(mark) >= len(fence):
                fence = None
            continue
        if fence is None:
            out.append((n, line))
    return out


def _rendered(heading: str) -> str:
    """The text GitHub renders for a heading's Markdown: code spans, links and emphasis unwrapped."""
    text = _CODE_SPAN.sub(lambda m: m.group(2).strip(), heading)
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", text)
    text = re.sub(r"<[^>]+>", "", text)
    text = re.sub(r"(\*{1,3})(\S.*?)\1", r"\2", text)
    return re.sub(r"(?<!\w)_{1,3}(\S.*?)_{1,3}(?!\w)", r"\1", text)


def slug(heading: str) -> str:
    """GitHub's anchor for one heading (before the ``-1``, ``-2`` of repeats)."""
    kept = (c for c in _rendered(heading).lower()
            if c in "- " or unicodedata.category(c)[0] in "LM" or unicodedata.category(c) in _KEPT)
    return "".join(kept).replace(" ", "-")


def anchors(text: str) -> set[str]:
    """Every anchor a page offers: its headings' slugs (repeats numbered) and explicit ids."""
    seen: dict[str, int] = {}
    out: set[str] = set()
    for _n, line in _prose_lines(text):
        out.update(_HTML_ID.findall(line))
        m = _HEADING.match(line)
        if not m:
            continue
        base = slug(m.group(2))
        count = seen.get(base, 0)
        seen[base] = count + 1
        out.add(base if count == 0 else f"{base}-{count}")
    return out


def links(text: str) -> list[tuple[int, str]]:
    """(line number, target) of every inline link or image outside code."""
    out = []
    for n, line in _prose_lines(text):
        for m in _LINK.finditer(_CODE_SPAN.sub("", line)):
            out.append((n, m.group(1)))
    return out


def broken_links(page: Path, root: Path = REPO) -> list[str]:
    """The page's relative links that do not resolve, as ``page:line: target: why``."""
    bad = []
    text = page.read_text(encoding="utf-8")
    for n, target in links(text):
        if not target or re.match(r"^[a-zA-Z][a-zA-Z0-9+.-]*:", target):
            continue   # a URL (https:, mailto:, …), not a file in this repository
        path_part, _, anchor = target.partition("#")
        dest = (page.parent / unquote(path_part)).resolve() if path_part else page
        where = f"{page.relative_to(root)}:{n}: {target}"
        if not dest.exists():
            bad.append(f"{where}: no such file")
        elif anchor and dest.suffix == ".md":
            if unquote(anchor) not in anchors(dest.read_text(encoding="utf-8")):
                bad.append(f"{where}: no heading with that anchor in {dest.name}")
    return bad


def test_every_relative_link_and_anchor_resolves():
    checked = pages()
    assert REPO / "README.md" in checked and any(p.parent.name == "docs" for p in checked)
    bad = [b for p in checked for b in broken_links(p)]
    assert not bad, "broken links:\n" + "\n".join(bad)


def test_the_readme_links_to_every_reference_page():
    readme = REPO / "README.md"
    targets = {t.partition("#")[0] for _n, t in links(readme.read_text(encoding="utf-8"))}
    for page in sorted((REPO / "docs").glob("*.md")):
        assert f"docs/{page.name}" in targets, f"README's contents do not link docs/{page.name}"


def test_readme_stays_short():
    assert len((REPO / "README.md").read_text(encoding="utf-8").splitlines()) <= 450


@pytest.mark.parametrize("heading, expected", [
    # GitHub's own example (docs.github.com, "Section links")
    ("This'll be a _Helpful_ Section About the Greek Letter Θ!",
     "thisll-be-a-helpful-section-about-the-greek-letter-θ"),
    ("Outputs (in `--out`, default `./audit`)", "outputs-in---out-default-audit"),
    ("What is checked (as ros2_control: |value| ≤ max is OK)",
     "what-is-checked-as-ros2_control-value--max-is-ok"),
    ("Acceleration estimate (q̈̂)", "acceleration-estimate-q̈̂"),
    ("~/controller_status", "controller_status"),
    ("Python client (`dyn_node.client`)", "python-client-dyn_nodeclient"),
    ("**Bold** and [a link](x.md)", "bold-and-a-link"),
])
def test_slug_follows_githubs_rule(heading, expected):
    assert slug(heading) == expected


def test_the_checker_finds_broken_files_and_anchors(tmp_path):
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "page.md").write_text("# Page\n\n## Exit codes\n\n## Exit codes\n")
    readme = tmp_path / "README.md"
    readme.write_text(
        "# Top\n\n"
        "[ok](docs/page.md#exit-codes) [ok 2](docs/page.md#exit-codes-1) [self](#top) "
        "[web](https://example.com/x#y)\n"
        "[gone](docs/missing.md) [bad anchor](docs/page.md#exit-codes-2) [bad self](#nowhere)\n"
        "```\n[in code](docs/missing2.md)\n```\n"
        "`[in a code span](docs/missing3.md)`\n")
    bad = broken_links(readme, root=tmp_path)
    assert [b.split(": ")[1] for b in bad] == ["docs/missing.md", "docs/page.md#exit-codes-2",
                                              "#nowhere"], bad
    assert all(b.startswith("README.md:4: ") for b in bad)
