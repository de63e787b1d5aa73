"""The README and the pages under docs/, checked like code (no Sphinx, no network).

Every check runs on the real files and, once, on a broken copy, which it must reject.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from docs_checks import (
    anchors,
    broken_links,
    cli_subcommands,
    readme_commands,
    slug,
    unreferenced_images,
)

from haptic_topology.cli import build_parser
from haptic_topology.config.node_params import KNOWN

REPO = Path(__file__).resolve().parents[2]
DOCS = REPO / 'docs'
README = REPO / 'README.md'
README_MAX_LINES = 250


def pages() -> list[Path]:
    """Every source page of the site (Markdown and reST), without the build output."""
    return sorted(p for p in DOCS.rglob('*') if p.suffix in ('.md', '.rst')
                  and '_build' not in p.parts)


# -- the README ----------------------------------------------------------------------------------
def test_readme_stays_short() -> None:
    lines = README.read_text(encoding='utf-8').splitlines()
    assert len(lines) <= README_MAX_LINES, (
        f'README.md has {len(lines)} lines (at most {README_MAX_LINES}): move detail into docs/')


def test_readme_command_table_lists_exactly_the_cli_subcommands() -> None:
    """The table in "## Command line" names each subcommand of the argument parser once, in
    the parser's order: a new subcommand without a README row fails here."""
    want = cli_subcommands(build_parser())
    got = readme_commands(README.read_text(encoding='utf-8'))
    assert got == want


def test_the_command_table_check_sees_a_missing_and_an_extra_row() -> None:
    readme = README.read_text(encoding='utf-8')
    want = cli_subcommands(build_parser())
    row = next(line for line in readme.splitlines()
               if line.startswith('| `haptic-topology device-server'))
    assert readme_commands(readme.replace(row + '\n', '')) != want
    extra = readme.replace(row, row + '\n| `haptic-topology teleport` | not a command |')
    assert readme_commands(extra) != want


def test_readme_links_into_every_page_of_the_site() -> None:
    """A newcomer reaches every page of the site's table of contents in one click from the
    README (the API reference through its index page)."""
    readme = README.read_text(encoding='utf-8')
    linked = set(re.findall(r'\]\(docs/([\w/.-]+?)(?:#[\w-]+)?\)', readme))
    index = (DOCS / 'index.md').read_text(encoding='utf-8')
    toc = set(re.findall(r'^(?!:)([\w/]+)$', index.split('```{toctree}', 1)[1], re.M))
    missing = sorted(entry for entry in toc
                     if f'{entry}.md' not in linked and f'{entry}.rst' not in linked)
    assert not missing, f'pages the README does not link to: {missing}'


# -- images and links ----------------------------------------------------------------------------
def test_every_image_under_docs_is_shown_on_a_page() -> None:
    assert unreferenced_images(DOCS, [*pages(), README]) == []


def test_the_image_check_sees_an_unreferenced_image(tmp_path: Path) -> None:
    (tmp_path / 'img').mkdir()
    (tmp_path / 'img' / 'shown.png').write_bytes(b'')
    (tmp_path / 'img' / 'orphan.png').write_bytes(b'')
    page = tmp_path / 'page.md'
    page.write_text('# Page\n\n![a figure](img/shown.png)\n\n'
                    '```\n![not here](img/orphan.png)\n```\n')
    assert unreferenced_images(tmp_path, [page]) == ['img/orphan.png']


@pytest.mark.parametrize('page', [README, *pages()], ids=lambda p: str(p.relative_to(REPO)))
def test_every_relative_link_resolves(page: Path) -> None:
    assert broken_links(page, REPO) == []


def test_the_link_check_sees_a_missing_file_and_a_missing_anchor(tmp_path: Path) -> None:
    (tmp_path / 'other.md').write_text('# Other\n\n## A section: `code` here\n')
    page = tmp_path / 'page.md'
    page.write_text('[ok](other.md#a-section-code-here) [web](https://example.org/x)\n'
                    '[gone](missing.md) [bad anchor](other.md#no-such-section)\n')
    assert broken_links(page, tmp_path) == [
        'missing.md', 'other.md#no-such-section (no heading with that anchor)']


def test_slug_is_myst_s() -> None:
    assert slug('A device on its own computer: `backend: network` and x') == (
        'a-device-on-its-own-computer-backend-network-and-x')
    assert 'the-loop-in-a-process-of-its-own' in anchors(
        (DOCS / 'nodes.md').read_text(encoding='utf-8'))


# -- generated pages -----------------------------------------------------------------------------
def test_the_parameter_page_has_a_generated_table_for_every_node() -> None:
    """docs/parameters.md holds one ``haptic-params`` directive per node whose settings class
    declares parameters: the rows come from the class when the site builds
    (test_docs_site checks the rendered rows)."""
    text = (DOCS / 'parameters.md').read_text(encoding='utf-8')
    directives = re.findall(r'^```\{haptic-params\}\s+(\w+)\s*$', text, re.M)
    assert directives == [node for node, specs in KNOWN.items() if specs is not None]


# -- nothing of how the project was built --------------------------------------------------------
@pytest.mark.parametrize('pattern', ['/tmp/', 'earlier version', 'nothing staged'])
def test_no_build_history_in_the_docs(pattern: str) -> None:
    hits = [f'{p.relative_to(REPO)}:{i}' for p in [README, *pages()]
            for i, line in enumerate(p.read_text(encoding='utf-8').splitlines(), 1)
            if pattern in line.lower()]
    assert hits == []
