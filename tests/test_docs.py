"""The documentation holds together: every relative link of the README and docs/ points to a file that exists, and the
user's page of the solver stays a page (issue 26: at most 20,000 characters; records of measurements go to
docs/decisions/)."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")


def _pages() -> list[Path]:
    return [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


def test_relative_links_point_to_files() -> None:
    broken = []
    for page in _pages():
        for target in LINK.findall(page.read_text(encoding="utf-8")):
            if re.match(r"^[a-z]+:", target) or target.startswith("#"):
                continue  # web addresses and anchors in the page itself
            path = (page.parent / target.split("#")[0]).resolve()
            if not path.exists():
                broken.append(f"{page.relative_to(ROOT)}: {target}")
    assert not broken, broken


def test_the_solver_page_is_a_users_page_and_links_the_records() -> None:
    text = (ROOT / "docs" / "solver.md").read_text(encoding="utf-8")
    assert len(text) <= 20_000, len(text)
    index = (ROOT / "docs" / "decisions" / "README.md").read_text(encoding="utf-8")
    for record in sorted((ROOT / "docs" / "decisions").glob("*.md")):
        if record.name != "README.md":
            assert f"]({record.name})" in index, f"{record.name} is not in docs/decisions/README.md"
