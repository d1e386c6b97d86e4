"""Merge several benchmark JSON files into one: {name_of_file_without_suffix: contents}."""

import json
import sys
from pathlib import Path

out = Path(sys.argv[1])
merged = {}
for name in sys.argv[2:]:
    p = Path(name)
    if p.exists():
        merged[p.stem] = json.loads(p.read_text())
out.write_text(json.dumps(merged, indent=2))
print(f"bench figures written to {out}")
