"""The docs cite what exists: every benchmark script a doc or the README names is in benchmarks/ (figures
whose script was never committed cannot be reproduced, issue 31)."""
from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOCS = sorted((ROOT / "docs").glob("*.md")) + [ROOT / "README.md"]


def test_every_benchmark_script_the_docs_cite_exists():
    cited = {}
    for doc in DOCS:
        text = doc.read_text()
        # `benchmarks/x.py`, or `bench_x.py` alone in a paragraph that already said where
        names = (re.findall(r"benchmarks/(\w+\.(?:py|sh))\b", text)
                 + re.findall(r"\b((?:bench|diag|profile)_\w+\.py)\b", text))
        for name in names:
            cited.setdefault(name, doc.name)
    assert cited, "no benchmark cited: the pattern no longer matches the docs"
    missing = {name: doc for name, doc in cited.items() if not (ROOT / "benchmarks" / name).is_file()}
    assert not missing, f"benchmark scripts cited but not in benchmarks/: {missing}"
