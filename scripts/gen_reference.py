"""The manual's reference pages, generated from the code so that they cannot drift.

- `reference.cli.cli_page()`: every command and option of the `flytrack` command (the typer app in
  flytrack_host.cli, walked as click sees it).
- `reference.rig_rules.rig_page()`, `rules_page()`: every field of the rig file
  (flytrack_host.rig.RigConfig) and of the rules file (flytrack_host.actuation.rules.RuleSet): type,
  default, unit, description, example (walked by reference.models).
- `reference.recording.recording_page()`: every table of a recording and its columns
  (flytrack_host.recording.schema), with the notes below (TABLE_NOTES).

This file says where each page goes (PAGES) and writes them; the package scripts/reference/ makes them.
`make docs` builds them through the MkDocs hook scripts/mkdocs_hooks.py (nothing generated is kept
in docs/); `python scripts/gen_reference.py OUT_DIR` writes them to a folder to read.
tests/docs/test_reference.py checks them against the code in both directions.
"""

from __future__ import annotations

import sys
from pathlib import Path

# scripts/ is on the path: Python puts it there for `python scripts/gen_reference.py`, mkdocs_hooks.py and
# tests/docs/test_reference.py put it there themselves.
from reference.cli import cli_page
from reference.recording import recording_page
from reference.rig_rules import rig_page, rules_page

# Where each generated page goes, under docs/.
CLI_PAGE = "reference/cli.md"
RIG_PAGE = "reference/rig-file.md"
RULES_PAGE = "reference/rules-file.md"
RECORDING_PAGE = "reference/recording.md"


PAGES = {CLI_PAGE: cli_page, RIG_PAGE: rig_page, RULES_PAGE: rules_page, RECORDING_PAGE: recording_page}


def main(argv: list[str]) -> int:
    if len(argv) != 1:
        print("usage: gen_reference.py OUT_DIR", file=sys.stderr)
        return 2
    out = Path(argv[0])
    for rel, make in PAGES.items():
        path = out / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(make())
        print(path)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
