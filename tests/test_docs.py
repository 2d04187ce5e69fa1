"""The README is a manual: at most 300 lines, and every relative link (and #anchor) in README.md, CHANGELOG.md
and docs/*.md points to a file (and heading) that exists."""

from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
FILES = [REPO / "README.md", REPO / "CHANGELOG.md", *sorted((REPO / "docs").glob("*.md"))]


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces as hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def anchors(path: Path) -> set[str]:
    out, in_code = set(), False
    for line in path.read_text().splitlines():
        if line.startswith("```"):
            in_code = not in_code
        if not in_code and line.startswith("#"):
            out.add(slug(line.lstrip("#")))
    return out


def test_readme_is_at_most_300_lines():
    n = len((REPO / "README.md").read_text().splitlines())
    assert n <= 300, f"README.md has {n} lines"


def test_every_relative_link_resolves():
    bad = []
    for f in FILES:
        text = re.sub(r"```.*?```", "", f.read_text(), flags=re.S)
        for m in re.finditer(r"!?\[[^\]]*\]\(([^)\s]+)\)", text):
            link = m.group(1)
            if re.match(r"[a-z]+://", link) or link.startswith("mailto:"):
                continue
            target, _, frag = link.partition("#")
            path = (f.parent / target).resolve() if target else f
            if not path.exists():
                bad.append(f"{f.relative_to(REPO)}: {link} (no such file)")
            elif frag and path.suffix == ".md" and frag not in anchors(path):
                bad.append(f"{f.relative_to(REPO)}: {link} (no such heading)")
    assert not bad, "\n".join(bad)
