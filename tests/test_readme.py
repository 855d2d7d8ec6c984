"""The README documents what the code writes."""

from __future__ import annotations

from pathlib import Path

from pavemap.export.geojson import PROPERTY_SCHEMA

README = Path(__file__).resolve().parents[1] / "README.md"


def test_readme_documents_every_defect_property():
    """Every key of the one defect schema appears backticked in README.md (its "Defect schema" table)."""
    text = README.read_text(encoding="utf-8")
    missing = [name for name, *_ in PROPERTY_SCHEMA if f"`{name}`" not in text]
    assert not missing, f"README.md does not document these defect properties: {', '.join(missing)}"
