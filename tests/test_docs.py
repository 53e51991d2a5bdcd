"""The README is the five-minute page and docs/ holds the rest: the README stays short and names the two commands
the Makefile runs, and every relative link of README.md, docs/*.md and notebooks/README.md resolves (the file,
and the heading an anchor names). The config reference on docs/configuration.md: tests/test_config_reference.py."""
from __future__ import annotations

import glob
import os
import re

import pytest

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
README = os.path.join(REPO, "README.md")
PAGES = [README, *sorted(glob.glob(os.path.join(REPO, "docs", "*.md"))),
         os.path.join(REPO, "notebooks", "README.md")]
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")


def _read(path: str) -> str:
    with open(path, encoding="utf-8") as f:
        return f.read()


def _prose(text: str) -> str:
    """The text outside fenced code blocks (links in code are not links)."""
    return re.sub(r"^```.*?^```", "", text, flags=re.S | re.M)


def _slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return text.replace(" ", "-")


def _anchors(path: str) -> set[str]:
    return {_slug(m.group(1)) for m in re.finditer(r"^#{1,6}\s+(.+?)\s*#*$", _prose(_read(path)), re.M)}


def test_readme_is_short_and_docs_hold_the_rest():
    lines = _read(README).splitlines()
    assert len(lines) < 350, f"README.md has {len(lines)} lines; move detail to docs/"
    for page in ("configuration", "data", "runs", "evaluation", "viewer", "architecture", "benchmarks",
                 "remapping", "slam"):
        path = os.path.join(REPO, "docs", f"{page}.md")
        assert os.path.isfile(path), path
        assert f"(docs/{page}.md)" in _read(README), f"README.md does not link docs/{page}.md"


def test_readme_names_the_two_commands_of_the_makefile():
    readme, makefile = _read(README), _read(os.path.join(REPO, "Makefile"))
    for target in ("demo", "test"):
        assert re.search(rf"^{target}:", makefile, re.M), target
        assert re.search(rf"^make {target}\s", readme, re.M), f"README.md does not show `make {target}`"


def test_pyproject_readme_is_the_readme():
    assert re.search(r'^readme = "README.md"$', _read(os.path.join(REPO, "pyproject.toml")), re.M)


@pytest.mark.parametrize("page", PAGES, ids=lambda p: os.path.relpath(p, REPO))
def test_relative_links_resolve(page):
    text = _read(page)
    assert "../shared/" not in text, f"{page} refers to a ../shared/ document"
    bad = []
    for target in LINK.findall(_prose(text)):
        if re.match(r"[a-z]+:", target):  # http(s), mailto
            continue
        file, _, anchor = target.partition("#")
        path = os.path.normpath(os.path.join(os.path.dirname(page), file)) if file else page
        if not os.path.exists(path):
            bad.append(f"{target} (no file {os.path.relpath(path, REPO)})")
        elif anchor and path.endswith(".md") and anchor not in _anchors(path):
            bad.append(f"{target} (no heading #{anchor} in {os.path.relpath(path, REPO)})")
    assert not bad, f"{os.path.relpath(page, REPO)}: broken links: {bad}"


def test_slug():
    assert _slug("Quality: the validation suite") == "quality-the-validation-suite"
    assert _slug("SLAM: `jaxmap bench slam`") == "slam-jaxmap-bench-slam"
    assert _slug("Running, stopping, resuming") == "running-stopping-resuming"


def test_the_help_says_what_synth_frames_and_eval_do():
    """Issue 43: `synth --frames` spreads the loop (it does not shorten the drive) and says how to map part
    of a drive; `eval` scores a run's mesh on the frames the run mapped."""
    from jaxmap.cli import build_parser

    sub = next(a for a in build_parser()._actions if a.dest == "command").choices
    frames = next(a for a in sub["synth"]._actions if a.dest == "frames").help
    assert "whole closed loop" in frames and "not shorter" in frames and "data.end_frame=N" in frames
    assert "frames the run mapped" in next(a for a in sub["eval"]._actions if a.dest == "frames").help
    readme = _read(README)
    for claim in ("runs/city/mesh_0.2.ply", "--no-mesh", "`synth --frames N` keeps the preset's whole loop",
                  "when it has timestamps", "jaxmap configs"):
        assert claim in readme, claim
