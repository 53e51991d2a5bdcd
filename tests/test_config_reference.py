"""The config reference (docs/configuration.md) is generated from the config dataclasses and cannot drift from
them: every key of every config root has a row there, and the page's block is what the generator writes."""
from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass, field

import pytest

from jaxmap import config_reference as cr
from jaxmap.config import ImtConfig, MapConfig, TrainConfig
from jaxmap.config import PriorConfig
from jaxmap.config import SlamConfig

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PAGE = os.path.join(REPO, "docs", "configuration.md")
README = os.path.join(REPO, "README.md")
FIX = "python -m jaxmap.config_reference --write"


def test_the_roots_are_every_config_root():
    assert [entry[1] for entry in cr.ROOTS] == [MapConfig, ImtConfig, SlamConfig, PriorConfig]
    assert os.path.join(REPO, cr.PAGE) == PAGE


def test_every_key_of_every_root_has_a_row_on_the_page():
    """Read from the page itself, not from the generator: a key (of any root or nested section) without a
    row under its root's heading in docs/configuration.md fails here, whatever the generator says."""
    missing = cr.undocumented_keys(PAGE)
    assert missing == [], (
        f"{len(missing)} config keys have no row in docs/configuration.md: {missing[:20]}; run `{FIX}` and "
        "commit docs/configuration.md")
    documented = cr.documented_keys(PAGE)
    for entry in cr.ROOTS:
        keys = [leaf.key for leaf in cr.iter_leaves(entry[1])]
        assert len(keys) > 5 and set(keys) <= documented[entry[0]], entry[0]
    # nested sections are there too (SlamConfig.frontend.odometry, PriorConfig.model.encoder)
    assert "frontend.odometry.method" in documented[cr.ROOTS[2][0]]
    assert any(k.startswith("model.encoder.") for k in documented[cr.ROOTS[3][0]])


def test_page_block_is_the_generated_reference():
    have = cr.page_block(PAGE)
    diff = cr.check(PAGE)
    assert have == cr.config_reference(), (
        "docs/configuration.md's config reference (between the config-reference markers) is out of date with "
        f"the config dataclasses; run `{FIX}` and commit docs/configuration.md.\n" + "\n".join(diff[:60]))
    assert cr.check() == [] and cr.page_block() == have  # the default page is this one


def test_the_reference_lives_in_docs_not_in_the_readme():
    with open(README) as f:
        readme = f.read()
    assert cr.BEGIN not in readme and "| `train.iters` |" not in readme
    assert "docs/configuration.md" in readme


def test_a_missing_key_fails_the_check(tmp_path, capsys):
    """Delete one key's row from a page: the key is reported missing and --check fails."""
    text = f"# Configuration\n\nprose\n\n{cr.BEGIN}\n{cr.config_reference()}{cr.END}\n"
    row = next(line for line in text.splitlines() if line.startswith("| `frontend.loops."))
    key = row.split("`")[1]
    page = tmp_path / "configuration.md"
    page.write_text(text.replace(row + "\n", "", 1))
    assert cr.undocumented_keys(str(page)) == [f"{cr.ROOTS[2][0]}: {key}"]
    capsys.readouterr()
    assert cr.main(["--check", str(page)]) == 1
    err = capsys.readouterr().err
    assert key in err and f"{FIX} {page}" in err
    assert cr.main(["--write", str(page)]) == 0 and cr.undocumented_keys(str(page)) == []
    assert page.read_text() == text


def test_every_leaf_field_of_every_root_is_documented():
    text = cr.config_reference()
    for entry in cr.ROOTS:
        title, root = entry[0], entry[1]
        assert f"### {title}" in text
        leaves = list(cr.iter_leaves(root))
        assert leaves, root
        for leaf in leaves:
            assert f"| `{leaf.key}` |" in text, f"{root.__name__}: {leaf.key} missing from the reference"
    assert cr.missing_descriptions() == [], (
        "these config fields have no description: add a trailing `# comment` to the field in its dataclass")


def test_every_description_is_non_empty_and_pending_entries_are_still_needed():
    """A PENDING_DESCRIPTIONS entry must name a real field that has no dataclass or YAML comment; once
    the dataclass gets a comment, the entry must go (so there is one source of truth)."""
    leaves = {}
    for entry in cr.ROOTS:
        notes = cr.yaml_comments(cr._root_yaml(entry))
        for leaf in cr.iter_leaves(entry[1]):
            text, source = cr.describe(leaf, notes)
            assert text.strip(), f"{entry[1].__name__}: {leaf.key} has no description"
            leaves[cr.pending_key(leaf)] = source
    for key in cr.PENDING_DESCRIPTIONS:
        assert key in leaves, f"PENDING_DESCRIPTIONS names {key}, which is not a config field"
        assert leaves[key] == "pending", (
            f"{key} now has a {leaves[key]} comment: delete its entry from PENDING_DESCRIPTIONS")


# A copy of the map config whose only difference is one default (train.iters 50 -> 51).
@dataclass(frozen=True)
class _TrainChanged(TrainConfig):
    iters: int = 51                  # K iterations per frame


@dataclass(frozen=True)
class _MapChanged(MapConfig):
    train: _TrainChanged = field(default_factory=_TrainChanged)


def test_a_changed_default_fails_the_check(tmp_path, monkeypatch, capsys):
    readme = tmp_path / "README.md"
    readme.write_text(f"# x\n\nprose\n\n{cr.BEGIN}\n{cr.config_reference()}{cr.END}\n\nmore prose\n")
    assert cr.check(str(readme)) == []
    assert cr.main(["--check", str(readme)]) == 0
    roots = [(t, _MapChanged if r is MapConfig else r, *rest) for t, r, *rest in cr.ROOTS]
    monkeypatch.setattr(cr, "ROOTS", roots)
    diff = cr.check(str(readme))
    changed = [line for line in diff if line.startswith(("-|", "+|"))]
    assert changed == ["-| `train.iters` | int | `50` | K iterations per frame |",
                       "+| `train.iters` | int | `51` | K iterations per frame |"], diff
    capsys.readouterr()
    assert cr.main(["--check", str(readme)]) == 1
    assert f"{FIX} {readme}" in capsys.readouterr().err
    # --write repairs the block and leaves the rest of the file alone
    assert cr.main(["--write", str(readme)]) == 0
    text = readme.read_text()
    assert text.startswith("# x\n\nprose\n\n") and text.endswith(f"{cr.END}\n\nmore prose\n")
    assert "| `train.iters` | int | `51` |" in text and cr.check(str(readme)) == []


def test_comment_sources(tmp_path):
    """Dataclass trailing comments (inherited fields from their declaring class), YAML fallback with
    aligned continuation lines, and quotes protecting a '#'."""
    notes = cr.dataclass_comments(TrainConfig)
    assert notes["iters"] == "K iterations per frame" and notes["lr"].startswith("Adam learning rate")
    leaf = {lf.key: lf for lf in cr.iter_leaves(_MapChanged)}
    assert leaf["train.lr"].owner is TrainConfig and leaf["train.iters"].owner is _TrainChanged
    y = tmp_path / "c.yaml"
    y.write_text("a:\n  b: 1          # first part\n                # second part\n  c: '#x'  # real\n"
                 "  d: 2\nd: x # top\n")
    assert cr.yaml_comments(str(y)) == {"a.b": "first part second part", "a.c": "real", "d": "top"}
    city = cr.yaml_comments(os.path.join(REPO, "configs", "city.yaml"))
    assert city["sampling.label_mode"] == "normal | projective | corrected"
    assert city["sampling.sigma_m"].endswith("(|grad f| ~ 1)")
    assert "\\|" in cr._cell(city["sampling.label_mode"])


def test_missing_markers_is_an_error(tmp_path):
    readme = tmp_path / "README.md"
    readme.write_text("no markers\n")
    with pytest.raises(SystemExit, match="config-reference:begin"):
        cr.check(str(readme))


def test_roots_are_dataclasses():
    for entry in cr.ROOTS:
        assert dataclasses.is_dataclass(entry[1]) and isinstance(entry[0], str)
