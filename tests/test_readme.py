"""The README and the docs document what the code writes."""

from __future__ import annotations

import re
from pathlib import Path

from pavemap.export.geojson import PROPERTY_SCHEMA

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
OUTPUTS = ROOT / "docs" / "guide" / "outputs.md"


def test_docs_document_every_defect_property():
    """Every key of the one defect schema appears backticked in the outputs guide (its "Defect schema" table)."""
    text = OUTPUTS.read_text(encoding="utf-8")
    missing = [name for name, *_ in PROPERTY_SCHEMA if f"`{name}`" not in text]
    assert not missing, f"{OUTPUTS} does not document these defect properties: {', '.join(missing)}"


def test_readme_is_short_and_its_links_exist():
    """The README stays a five-minute read (<= 300 lines) and every file it links or shows exists."""
    text = README.read_text(encoding="utf-8")
    assert len(text.splitlines()) <= 300
    targets = re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text)
    local = [t for t in targets if "://" not in t]
    assert local, "README links nothing"
    missing = [t for t in local if not (ROOT / t).exists()]
    assert not missing, f"README links files that do not exist: {missing}"
