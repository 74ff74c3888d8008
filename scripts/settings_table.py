"""Print, check or rewrite the settings table of docs/settings.md, generated from the settings schema.

    python scripts/settings_table.py            # print the table
    python scripts/settings_table.py --check    # exit 1 when docs/settings.md's table differs
    python scripts/settings_table.py --write    # replace the table in docs/settings.md

The table lies between the two marker comments below; tests/test_schema.py checks it is up to date.
"""

from __future__ import annotations

import sys
from pathlib import Path

from napari_fdt.recon.settings.config import settings_markdown

DOC = Path(__file__).resolve().parents[1] / "docs" / "settings.md"
BEGIN = "<!-- settings table: generated from napari_fdt.recon.settings.config by scripts/settings_table.py --write; do not edit -->"
END = "<!-- end of the generated settings table -->"


def rewrite(text: str) -> str:
    """``text`` with the block between the markers replaced by the generated table."""
    head, sep, rest = text.partition(BEGIN)
    if not sep or END not in rest:
        raise SystemExit(f"{DOC}: markers not found ({BEGIN} ... {END})")
    return head + BEGIN + "\n" + settings_markdown() + END + rest.partition(END)[2]


def main(argv: list[str]) -> int:
    if argv == ["--write"]:
        DOC.write_text(rewrite(DOC.read_text(encoding="utf-8")), encoding="utf-8")
        return 0
    if argv == ["--check"]:
        text = DOC.read_text(encoding="utf-8")
        if rewrite(text) != text:
            print(f"{DOC}: settings table out of date: run python scripts/settings_table.py --write", file=sys.stderr)
            return 1
        return 0
    if argv:
        print(__doc__, file=sys.stderr)
        return 2
    sys.stdout.write(settings_markdown())
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
