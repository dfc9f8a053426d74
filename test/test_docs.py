"""The documentation agrees with the code: docs/ros.md's tables generated from the code, the sections README.md and
docs/ros.md point to, and the configuration keys and node parameters they name."""
from __future__ import annotations

import re
from pathlib import Path

import pytest

from eslam_core.config import Config
from eslam_ros.node_params import MARKDOWN_TABLES, config_parameters, node_parameter_defaults

REPO = Path(__file__).resolve().parent.parent
DOCS = ("README.md", "docs/ros.md")
GENERATED = re.compile(r"<!-- generated: python -m eslam_ros\.node_params --markdown (\w+)[^\n]*-->\n(.*?)\n"
                       r"<!-- end generated -->", re.S)
# A section named in prose: `see "X"`, `README, "X"`, `the README's "X"`, `(docs/ros.md, "X")`, `"X" below`.
REFERENCE = re.compile(r"(?:\b(README|docs/ros\.md)(?:'s|,)?\s+|\bsee\s+(?:the\s+)?)\"([^\"]+)\""
                       r"|\"([^\"]+)\"\s+(?:above|below)\b")
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")
FILE_SUFFIXES = ("ply", "json", "yaml", "txt", "pt", "py", "md", "xml", "c")


def _text(name: str) -> str:
    return (REPO / name).read_text()


def _prose(text: str) -> str:
    """The text without fenced code blocks, each run of white space one space (references wrap across lines)."""
    return re.sub(r"\s+", " ", re.sub(r"^```.*?^```", "", text, flags=re.S | re.M))


def _headings(text: str) -> list[str]:
    text = re.sub(r"^```.*?^```", "", text, flags=re.S | re.M)
    return [line.lstrip("#").strip() for line in text.splitlines() if re.match(r"#{1,6} ", line)]


def _slug(heading: str) -> str:
    """GitHub's anchor of a heading."""
    return re.sub(r"[^\w\- ]", "", heading.lower()).replace(" ", "-")


def _resolves(name: str, target: str) -> bool:
    """A heading of `target` starts with `name` (references shorten them: "The map frame")."""
    wanted = name.lower().replace("`", "")
    return any(h.lower().replace("`", "").startswith(wanted) for h in _headings(_text(target)))


@pytest.mark.parametrize("kind", sorted(MARKDOWN_TABLES))
def test_docs_tables_are_the_generated_ones(kind):
    blocks = dict(GENERATED.findall(_text("docs/ros.md")))
    assert kind in blocks, f"docs/ros.md has no generated '{kind}' block (python -m eslam_ros.node_params)"
    assert blocks[kind] == MARKDOWN_TABLES[kind](), (
        f"docs/ros.md's '{kind}' table is not the code's: replace the block with the output of "
        f"`python -m eslam_ros.node_params --markdown {kind}`")


@pytest.mark.parametrize("doc", DOCS)
def test_referenced_sections_exist(doc):
    missing = []
    for match in REFERENCE.finditer(_prose(_text(doc))):
        named, name = match.group(1), match.group(2) or match.group(3)
        target = {"README": "README.md", "docs/ros.md": "docs/ros.md"}.get(named, doc)
        if not _resolves(name, target):
            missing.append(f'"{name}" (in {target})')
    for match in LINK.finditer(_prose(_text(doc))):
        href = match.group(1)
        if href.startswith(("http://", "https://", "mailto:")):
            continue
        path, _, anchor = href.partition("#")
        target = (REPO / doc).parent / path if path else REPO / doc
        if not target.exists():
            missing.append(f"{href} (no such file)")
        elif anchor and anchor not in {_slug(h) for h in _headings(target.read_text())}:
            missing.append(f"{href} (no such heading)")
    assert not missing, f"{doc} points to sections that do not exist: {', '.join(missing)}"


@pytest.mark.parametrize("doc", DOCS)
def test_named_configuration_keys_and_node_parameters_exist(doc):
    """`section.key` of eslam_core's configuration (or `eslam.section.key`), and `sync.` / `odom.` /
    `diagnostics.` node parameters, wherever the docs name one in code spans."""
    keys = {name[len("eslam."):] for name in config_parameters(Config())}
    keys |= {key.rsplit(".", 1)[0] for key in keys}  # nested groups (tracking.weights)
    sections = {key.split(".")[0] for key in keys}
    node = set(node_parameter_defaults())
    groups = {name.split(".")[0] for name in node if "." in name}
    unknown = set()
    for span in re.findall(r"`([^`]+)`", _prose(_text(doc))):
        for match in re.finditer(r"(?<![\w./-])(?:eslam\.)?([a-z_]+)\.([a-z_]+(?:\.[a-z_]+)?)(?![\w(/-])", span):
            first, rest = match.groups()
            if rest.split(".")[-1] in FILE_SUFFIXES:
                continue
            name = f"{first}.{rest}"
            if (first in sections and name not in keys) or (first in groups and name not in node):
                unknown.add(name)
    assert not unknown, f"{doc} names keys that do not exist: {', '.join(sorted(unknown))}"
