"""Checks of the README and the documentation pages, as functions the tests apply to the real
files and to broken copies (so that each check is seen to fail).

No network, no Sphinx: plain text and the CLI's argument parser.
"""

from __future__ import annotations

import argparse
import re
from collections.abc import Iterable
from pathlib import Path

#: Files under docs/ that are pictures.
IMAGE_SUFFIXES = ('.png', '.jpg', '.jpeg', '.svg', '.gif')

_LINK = re.compile(r'(?<!\!)\[[^\]]*\]\(([^)\s]+)\)')
_IMAGE = re.compile(r'!\[[^\]]*\]\(([^)\s]+)\)')
_FENCE = re.compile(r'^(```|~~~)')


def cli_subcommands(parser: argparse.ArgumentParser) -> list[str]:
    """The subcommand names of ``parser``, in the order ``--help`` lists them."""
    for action in parser._actions:  # argparse keeps its subparsers only here
        if isinstance(action, argparse._SubParsersAction):
            return list(action.choices)
    raise AssertionError('the parser has no subcommands')


def readme_commands(readme: str) -> list[str]:
    """The subcommands of the README's command table (section ``## Command line``): the first
    word after ``haptic-topology`` in the first column of each row."""
    section = readme.split('\n## Command line', 1)
    if len(section) != 2:
        raise AssertionError('the README has no "## Command line" section')
    body = section[1].split('\n## ', 1)[0]
    out = []
    for line in body.splitlines():
        match = re.match(r'^\|\s*`haptic-topology ([\w-]+)', line)
        if match:
            out.append(match.group(1))
    return out


def prose_lines(text: str) -> Iterable[str]:
    """The lines of a Markdown text outside fenced code blocks."""
    fenced = False
    for line in text.splitlines():
        if _FENCE.match(line.strip()):
            fenced = not fenced
            continue
        if not fenced:
            yield line


def image_references(text: str) -> list[str]:
    """Targets of Markdown images ``![alt](target)`` outside code blocks."""
    return [m.group(1) for line in prose_lines(text) for m in _IMAGE.finditer(line)]


def unreferenced_images(docs: Path, pages: Iterable[Path]) -> list[str]:
    """Images under ``docs`` that no page (Markdown or reST) shows, relative to ``docs``."""
    shown: set[Path] = set()
    for page in pages:
        text = page.read_text(encoding='utf-8')
        targets = image_references(text) + re.findall(
            r'^\s*\.\. (?:image|figure)::\s*(\S+)', text, re.M)
        for target in targets:
            shown.add((page.parent / target).resolve())
    return sorted(str(p.relative_to(docs)) for p in docs.rglob('*')
                  if p.suffix.lower() in IMAGE_SUFFIXES and '_build' not in p.parts
                  and p.resolve() not in shown)


def slug(heading: str) -> str:
    """The anchor MyST (and GitHub) give a heading: lower case, punctuation dropped, spaces to
    hyphens."""
    text = re.sub(r'[`*]', '', heading.strip().lower())
    text = re.sub(r'[^\w\- ]', '', text)
    return text.replace(' ', '-')


def anchors(markdown: str) -> set[str]:
    """The heading anchors of a Markdown page: MyST's slug, and the section id Sphinx gives the
    same heading (docutils turns ``_`` into ``-``)."""
    slugs = {slug(m.group(2)) for line in prose_lines(markdown)
             if (m := re.match(r'^(#{1,6})\s+(.*)$', line))}
    return slugs | {s.replace('_', '-') for s in slugs}


def broken_links(page: Path, root: Path) -> list[str]:
    """Relative links and images of ``page`` whose file (or ``.md`` heading anchor) does not
    exist. Links to web addresses are not followed (the tests run offline). A link may not
    leave ``root``."""
    text = page.read_text(encoding='utf-8')
    targets = [m.group(1) for line in prose_lines(text) for m in _LINK.finditer(line)]
    targets += image_references(text)
    broken = []
    for target in targets:
        if re.match(r'^[a-z][a-z0-9+.-]*:', target):   # http:, https:, mailto:
            continue
        path_part, _, anchor = target.partition('#')
        path = (page.parent / path_part).resolve() if path_part else page.resolve()
        if root.resolve() not in path.parents and path != root.resolve():
            broken.append(f'{target} (outside the repository)')
        elif not path.exists():
            broken.append(target)
        elif anchor and path.suffix == '.md' and anchor not in anchors(
                path.read_text(encoding='utf-8')):
            broken.append(f'{target} (no heading with that anchor)')
    return broken
