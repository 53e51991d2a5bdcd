"""Markdown reference of every config key, generated from the config dataclasses.

    python -m jaxmap.config_reference           # print the reference
    python -m jaxmap.config_reference --check   # exit 1 if docs/configuration.md's block is out of date
    python -m jaxmap.config_reference --write   # rewrite docs/configuration.md's block
    python -m jaxmap.config_reference --check PAGE.md   # ... or another page's

The documentation page :data:`PAGE` (`docs/configuration.md`) holds the reference between the lines
`<!-- config-reference:begin -->` and `<!-- config-reference:end -->`; `tests/test_config_reference.py`
fails when that block differs from :func:`config_reference` or when a key of a config root is missing
from it (:func:`undocumented_keys`), so the documentation cannot drift from the dataclasses.

For each config root in :data:`ROOTS` there is one table per section (`data`, `train`, ...,
`model.encoder`, and the root's own keys under "top level"): dotted key, type, default (the
dataclass default, i.e. what a key left out of a YAML file gets) and a description. The description
is, in this order of preference:

1. the trailing ``# comment`` on the field's line in the dataclass source;
2. the trailing ``# comment`` on the key's line in the root's shipped YAML file;
3. an entry of :data:`PENDING_DESCRIPTIONS` (fields that have neither yet; the test fails when an
   entry there is no longer needed, so a comment added to the dataclass replaces it).

A comment continued on the next line(s) as comment-only lines whose ``#`` is aligned with the first
one is joined to it.
"""
from __future__ import annotations

import argparse
import ast
import dataclasses
import difflib
import functools
import inspect
import io
import json
import os
import re
import sys
import textwrap
import tokenize
import typing
from typing import Any, Iterator, NamedTuple

from jaxmap.config import ImtConfig, MapConfig
from jaxmap.config import PriorConfig
from jaxmap.config import SlamConfig

BEGIN = "<!-- config-reference:begin -->"
END = "<!-- config-reference:end -->"
REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PAGE = os.path.join("docs", "configuration.md")  # the page that holds the reference, relative to REPO

# One line per config root: (title, root dataclass[, shipped YAML for the comment fallback]).
# Without the third element, the first `configs/*.yaml` named in the title is used.
ROOTS: list[tuple] = [
    ("jaxmap map (configs/city.yaml, ncd.yaml, rgbd.yaml)", MapConfig),
    ("jaxmap imt (configs/room_imt.yaml)", ImtConfig),
    ("jaxmap slam (configs/room_slam.yaml, city_slam.yaml)", SlamConfig),
    ("jaxmap prior (configs/prior.yaml)", PriorConfig),
]

# Descriptions of fields that have no comment in their dataclass nor in the shipped YAML yet, keyed by
# "<declaring dataclass>.<field>". Move each into that dataclass as a trailing comment and delete it
# here (the test says which entries have become redundant).
PENDING_DESCRIPTIONS: dict[str, str] = {}


class Leaf(NamedTuple):
    key: str          # dotted key, e.g. "train.iters"
    section: str      # dotted section, "" for the root's own keys
    owner: type       # the dataclass that declares the field
    name: str         # the field name
    type: Any         # the resolved annotation
    default: Any      # the default value


# ---------------------------------------------------------------------------------------------
# Walking the dataclass tree
# ---------------------------------------------------------------------------------------------


def iter_leaves(cls: type, prefix: str = "", instance: Any = None) -> Iterator[Leaf]:
    """Every scalar (non-dataclass) field of the tree rooted at `cls`, in declaration order."""
    instance = cls() if instance is None else instance
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        value = getattr(instance, f.name)
        key = f"{prefix}{f.name}"
        if dataclasses.is_dataclass(value):
            yield from iter_leaves(type(value), f"{key}.", value)
        else:
            yield Leaf(key, prefix[:-1], _declaring_class(cls, f.name), f.name, hints[f.name], value)


def _declaring_class(cls: type, name: str) -> type:
    for klass in cls.__mro__:
        if name in klass.__dict__.get("__annotations__", {}):
            return klass
    return cls


# ---------------------------------------------------------------------------------------------
# Comments: dataclass source and YAML
# ---------------------------------------------------------------------------------------------


def _comment_text(raw: str) -> str:
    return raw.lstrip("#").strip()


def _join_continuations(lines: list[str], row: int, col: int, first: str) -> str:
    """`first` plus the following comment-only lines (0-based index `row` onwards) with `#` at `col`."""
    parts = [first]
    for line in lines[row + 1:]:
        stripped = line.lstrip()
        if not stripped.startswith("#") or len(line) - len(stripped) != col:
            break
        parts.append(_comment_text(stripped))
    return " ".join(p for p in parts if p)


@functools.lru_cache(maxsize=None)
def dataclass_comments(cls: type) -> dict[str, str]:
    """{field name: trailing comment} of the fields a dataclass declares (not inherited ones)."""
    try:
        src = textwrap.dedent(inspect.getsource(cls))
    except (OSError, TypeError):  # no source (built dynamically, or a frozen install)
        return {}
    lines = src.splitlines()
    comments: dict[int, tuple[int, str]] = {}  # 1-based line -> (column, text)
    for tok in tokenize.generate_tokens(io.StringIO(src).readline):
        if tok.type == tokenize.COMMENT:
            comments[tok.start[0]] = (tok.start[1], tok.string)
    (node,) = [n for n in ast.parse(src).body if isinstance(n, ast.ClassDef)][:1]
    out = {}
    for stmt in node.body:
        if isinstance(stmt, ast.AnnAssign) and isinstance(stmt.target, ast.Name):
            line = stmt.end_lineno or stmt.lineno
            if line in comments:
                col, text = comments[line]
                out[stmt.target.id] = _join_continuations(lines, line - 1, col, _comment_text(text))
    return out


_YAML_KEY = re.compile(r"^(?P<indent>\s*)(?P<key>[A-Za-z_][\w-]*)\s*:(?P<rest>.*)$")


def yaml_comments(path: str) -> dict[str, str]:
    """{dotted key: trailing comment} of a YAML config file (block style, as the shipped ones)."""
    if not path or not os.path.isfile(path):
        return {}
    with open(path) as f:
        lines = f.read().splitlines()
    out: dict[str, str] = {}
    stack: list[tuple[int, str]] = []  # (indent, key) of the enclosing mappings
    for row, line in enumerate(lines):
        m = _YAML_KEY.match(line)
        if not m:
            continue
        indent = len(m["indent"])
        while stack and stack[-1][0] >= indent:
            stack.pop()
        key = ".".join([k for _, k in stack] + [m["key"]])
        rest = m["rest"]
        hash_at = _comment_start(rest)
        if hash_at >= 0:
            col = len(line) - len(rest) + hash_at
            out[key] = _join_continuations(lines, row, col, _comment_text(rest[hash_at:]))
        if not rest.split("#", 1)[0].strip():  # a mapping opens here
            stack.append((indent, m["key"]))
    return out


def _comment_start(value: str) -> int:
    """Index of the `#` starting a comment in a YAML value (outside quotes, after whitespace), or -1."""
    quote = None
    for i, ch in enumerate(value):
        if quote:
            quote = None if ch == quote else quote
        elif ch in "\"'":
            quote = ch
        elif ch == "#" and (i == 0 or value[i - 1].isspace()):
            return i
    return -1


def _root_yaml(entry: tuple) -> str | None:
    if len(entry) > 2:
        return os.path.join(REPO, entry[2])
    m = re.search(r"configs/[\w.-]+\.yaml", entry[0])
    return os.path.join(REPO, m.group(0)) if m else None


def pending_key(leaf: Leaf) -> str:
    """The PENDING_DESCRIPTIONS key of a leaf: "<declaring dataclass>.<field>"."""
    return f"{leaf.owner.__name__}.{leaf.name}"


def describe(leaf: Leaf, yaml_notes: dict[str, str]) -> tuple[str, str]:
    """(description, source) of a leaf; source is "dataclass", "yaml", "pending" or "" (none)."""
    text = dataclass_comments(leaf.owner).get(leaf.name, "")
    if text:
        return text, "dataclass"
    if yaml_notes.get(leaf.key):
        return yaml_notes[leaf.key], "yaml"
    pending = PENDING_DESCRIPTIONS.get(pending_key(leaf), "")
    return pending, ("pending" if pending else "")


# ---------------------------------------------------------------------------------------------
# Markdown
# ---------------------------------------------------------------------------------------------


def _type_name(t: Any) -> str:
    origin = typing.get_origin(t)
    if origin is tuple:
        return f"list of {_type_name(typing.get_args(t)[0])}"
    return getattr(t, "__name__", str(t).replace("typing.", ""))


def _default(v: Any) -> str:
    if isinstance(v, tuple):
        v = list(v)
    return f"`{json.dumps(v)}`"


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def root_tables(entry: tuple) -> str:
    title, root = entry[0], entry[1]
    notes = yaml_comments(_root_yaml(entry))
    sections: dict[str, list[str]] = {}
    for leaf in iter_leaves(root):
        text, _ = describe(leaf, notes)
        row = f"| `{leaf.key}` | {_type_name(leaf.type)} | {_default(leaf.default)} | {_cell(text)} |"
        sections.setdefault(leaf.section, []).append(row)
    module = "jaxmap.config" if root.__module__.startswith("jaxmap.config.") else root.__module__  # the public path
    out = [f"### {title}", "", f"Root: `{module}.{root.__qualname__}`.", ""]
    for section, rows in sections.items():
        out += [f"**{section or 'top level'}**", "", "| key | type | default | description |",
                "|---|---|---|---|", *rows, ""]
    return "\n".join(out)


def config_reference(roots: list[tuple] | None = None) -> str:
    """The Markdown reference of every root (the text between the page's markers, newline-terminated)."""
    roots = ROOTS if roots is None else roots
    head = ("<!-- generated from the config dataclasses by `python -m jaxmap.config_reference --write`; "
            "do not edit by hand -->\n\n"
            "Defaults are the dataclass defaults, what a key left out of a YAML file gets; the shipped YAML "
            "files spell out every key and may set other values.\n")
    return head + "".join("\n" + root_tables(e) for e in roots)


def missing_descriptions(roots: list[tuple] | None = None) -> list[str]:
    """Fields (as "<declaring dataclass>.<field> (<dotted key>)") that have no description from any source."""
    out = []
    for entry in ROOTS if roots is None else roots:
        notes = yaml_comments(_root_yaml(entry))
        for leaf in iter_leaves(entry[1]):
            if not describe(leaf, notes)[0]:
                out.append(f"{pending_key(leaf)} ({leaf.key})")
    return out


# ---------------------------------------------------------------------------------------------
# The page's block
# ---------------------------------------------------------------------------------------------


def page_path(path: str | None = None) -> str:
    """`path`, or the reference page :data:`PAGE` of this checkout."""
    return path if path else os.path.join(REPO, PAGE)


def _split(text: str, path: str) -> tuple[str, str, str]:
    """(before incl. the BEGIN line, block, END line and after)."""
    b, e = text.find(BEGIN), text.find(END)
    if b < 0 or e < 0 or e < b:
        raise SystemExit(f"{path}: no '{BEGIN}' ... '{END}' block; add the two marker lines where the "
                         "reference should go")
    start = text.index("\n", b) + 1
    return text[:start], text[start:e], text[e:]


def page_block(path: str | None = None) -> str:
    """The text between the markers of `path` (default: :data:`PAGE`)."""
    path = page_path(path)
    with open(path) as f:
        return _split(f.read(), path)[1]


_ROW_KEY = re.compile(r"^\|\s*`([^`]+)`\s*\|")


def documented_keys(path: str | None = None) -> dict[str, set[str]]:
    """{root title: dotted keys that have a table row under that root's `### title` heading} of the block."""
    out: dict[str, set[str]] = {}
    title = None
    for line in page_block(path).splitlines():
        if line.startswith("### "):
            title = line[4:].strip()
            out.setdefault(title, set())
        elif title is not None:
            m = _ROW_KEY.match(line)
            if m:
                out[title].add(m.group(1))
    return out


def undocumented_keys(path: str | None = None, roots: list[tuple] | None = None) -> list[str]:
    """Every key of every root (as "<title>: <dotted key>") that has no row under its root in the page."""
    have = documented_keys(path)
    missing = []
    for entry in ROOTS if roots is None else roots:
        title, root = entry[0], entry[1]
        keys = have.get(title, set())
        missing += [f"{title}: {leaf.key}" for leaf in iter_leaves(root) if leaf.key not in keys]
    return missing


def check(path: str | None = None, roots: list[tuple] | None = None) -> list[str]:
    """Unified diff lines between the page's block and the generated reference ([] = up to date)."""
    path = page_path(path)
    want = config_reference(roots)
    have = page_block(path)
    if have == want:
        return []
    return list(difflib.unified_diff(have.splitlines(), want.splitlines(), f"{path} (block)",
                                     "config_reference()", lineterm=""))


def write(path: str | None = None, roots: list[tuple] | None = None) -> bool:
    """Rewrite the page's block; returns whether the file changed."""
    path = page_path(path)
    with open(path) as f:
        text = f.read()
    before, block, after = _split(text, path)
    want = config_reference(roots)
    if block == want:
        return False
    with open(path, "w") as f:
        f.write(before + want + after)
    return True


def _resolve(arg: str) -> str:
    """A page named on the command line: as given when it exists from here, else relative to the repository."""
    return arg if os.path.isabs(arg) or os.path.exists(arg) else os.path.join(REPO, arg)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m jaxmap.config_reference", description=__doc__.splitlines()[0])
    g = p.add_mutually_exclusive_group()
    g.add_argument("--check", metavar="PAGE", nargs="?", const=PAGE,
                   help=f"exit 1 if the page's block is out of date or misses a key (default page: {PAGE})")
    g.add_argument("--write", metavar="PAGE", nargs="?", const=PAGE,
                   help=f"rewrite the page's block (default page: {PAGE})")
    args = p.parse_args(argv)
    if args.check:
        path = _resolve(args.check)
        diff, missing = check(path), undocumented_keys(path)
        if diff or missing:
            print("\n".join(diff))
            if missing:
                print(f"\n{args.check}: {len(missing)} config keys missing: " + ", ".join(missing[:20]),
                      file=sys.stderr)
            fix = "" if args.check == PAGE else f" {args.check}"
            print(f"\n{args.check}: the config reference is out of date; run "
                  f"`python -m jaxmap.config_reference --write{fix}`", file=sys.stderr)
            return 1
        print(f"{args.check}: config reference up to date")
        return 0
    if args.write:
        path = _resolve(args.write)
        changed = write(path)
        print(f"{args.write}: {'config reference rewritten' if changed else 'config reference already up to date'}")
        return 0
    sys.stdout.write(config_reference())
    return 0


if __name__ == "__main__":
    sys.exit(main())
