"""The documentation: the MkDocs site builds with ``--strict`` (every broken link or anchor, page left out of the
navigation, or API reference that cannot be collected is an error), and the README stays a five-minute read."""

import os
import re
import subprocess
import sys

from conftest import ROOT

README_MAX_LINES = 300


def test_the_site_builds_strictly(tmp_path):
    env = dict(os.environ, NO_MKDOCS_2_WARNING="1")
    cmd = [sys.executable, "-m", "mkdocs", "build", "--strict", "--config-file", str(ROOT / "mkdocs.yml"),
           "--site-dir", str(tmp_path / "site")]
    r = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, check=False, timeout=300)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    site = tmp_path / "site"
    for page in ("index.html", "architecture.html", "extending.html", "api/scanreg.types.html"):
        assert (site / page).is_file(), page
    # the API reference was rendered from the docstrings, with cross-references resolved into links
    steps = (site / "api" / "scanreg.runner.steps.html").read_text()
    assert 'id="scanreg.runner.steps.prepare_scan"' in steps
    assert 'href="scanreg.types.html#scanreg.types.PreparedScan"' in steps
    protocols = (site / "api" / "scanreg.stages.protocols.html").read_text()
    assert 'id="scanreg.stages.protocols.FineStage.refine"' in protocols


def test_the_readme_is_short_and_links_to_existing_pages():
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= README_MAX_LINES
    assert "./run docs" in text
    pages = re.findall(r"\]\((docs/[^)#]+)", text)
    assert pages, "the README links to the documentation pages"
    assert all((ROOT / p).is_file() for p in pages), [p for p in pages if not (ROOT / p).is_file()]
