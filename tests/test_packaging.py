"""What PyPI and the napari hub read: classifiers, extras, LICENSE matching the declared license, CITATION.cff."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from napari_fdt._version import __version__

ROOT = Path(__file__).resolve().parents[1]


def _project() -> dict:
    tomllib = pytest.importorskip("tomllib")  # Python >= 3.11
    return tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]


def test_metadata_for_pypi_and_the_napari_hub() -> None:
    project = _project()
    assert "Framework :: napari" in project["classifiers"]
    assert "napari" in project["keywords"] and project["authors"]
    # the core installs headless: no napari, Qt or magicgui among the plain dependencies
    plain = " ".join(project["dependencies"]).lower()
    assert not any(gui in plain for gui in ("napari", "qt", "magicgui", "superqt", "npe2"))
    extras = project["optional-dependencies"]
    assert any(d.startswith("napari>=") for d in extras["napari"])
    bindings = ("pyqt5", "pyqt6", "pyside2", "pyside6", "napari[qt]", "napari[all]", "napari[pyqt")
    assert "napari[qt]" in extras["test"] and not any(d.lower().startswith(bindings) for d in extras["napari"])
    assert project["entry-points"]["napari.manifest"]["napari-fdt"] == "napari_fdt.napari:napari.yaml"


def test_license_file_matches_the_declared_license() -> None:
    declared = _project()["license"]["text"]
    text = (ROOT / "LICENSE").read_text(encoding="utf-8")
    assert declared == "BSD-3-Clause" and text.startswith("BSD 3-Clause License")
    assert "License :: OSI Approved :: BSD License" in _project()["classifiers"]


def test_citation_file_cites_the_paper() -> None:
    cff = yaml.safe_load((ROOT / "CITATION.cff").read_text(encoding="utf-8"))
    assert cff["cff-version"] == "1.2.0" and cff["version"] == __version__ and cff["license"] == "BSD-3-Clause"
    paper = cff["preferred-citation"]
    seed = Path("/work/shared/seed/000_a7b8e037b4bc27e1.txt")
    assert paper["title"] == "Fluorescence Diffraction Tomography using Explicit Neural Fields"
    assert [a["family-names"] for a in paper["authors"]] == ["He", "Li", "Chen", "Xue"]
    if seed.is_file():  # the paper's own title and authors, where the source is at hand
        tex = seed.read_text(encoding="utf-8")
        assert paper["title"] in tex and all(f"\\sur{{{a['family-names']}}}" in tex for a in paper["authors"])
