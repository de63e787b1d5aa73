"""Sphinx directive ``haptic-equations``: the paper's equation numbers -> the code that implements
them, collected from the docstrings while the site builds.

Usage (MyST)::

    ```{haptic-equations}
    ```

Every public class, function and method of the core packages whose docstring cites
``eq. N`` / ``eqs. N-M`` is listed under each of those numbers, linked to its API entry, so the
table follows the docstrings instead of being kept by hand.
"""

from __future__ import annotations

import ast
import re
from collections import defaultdict
from pathlib import Path
from typing import Any

from docutils import nodes
from docutils.parsers.rst import Directive
from sphinx import addnodes
from sphinx.application import Sphinx

import haptic_topology

#: Packages whose docstrings are collected (the core; their API pages document every name).
CORE = ('model', 'dynamics', 'control', 'device', 'sim')
CITE = re.compile(r'\beqs?\.\s*(\d+)(?:\s*-\s*(\d+))?((?:\s*,\s*\d+(?:\s*-\s*\d+)?)*)')


def _numbers(doc: str) -> set[int]:
    """Equation numbers a docstring cites (``eq. 14``, ``eqs. 17-20``, ``eqs. 1, 2, 10``)."""
    out: set[int] = set()
    for match in CITE.finditer(doc):
        for part in match.group(0).split('.', 1)[1].split(','):
            bounds = [int(b) for b in re.findall(r'\d+', part)]
            if len(bounds) == 1:
                out.add(bounds[0])
            elif len(bounds) == 2 and 0 <= bounds[1] - bounds[0] <= 10:
                out.update(range(bounds[0], bounds[1] + 1))
    return out


def equation_index() -> dict[int, list[tuple[str, str]]]:
    """Equation number -> sorted ``(role, dotted name)`` of the public objects citing it."""
    root = Path(haptic_topology.__file__).resolve().parent
    index: dict[int, set[tuple[str, str]]] = defaultdict(set)
    for package in CORE:
        for path in sorted((root / package).rglob('*.py')):
            if path.name.startswith('_'):
                continue
            module = 'haptic_topology.' + '.'.join(path.relative_to(root).with_suffix('').parts)
            tree = ast.parse(path.read_text(encoding='utf-8'))

            def visit(node: ast.AST, prefix: str, in_class: bool, module: str = module) -> None:
                for child in ast.iter_child_nodes(node):
                    if not isinstance(child, ast.FunctionDef | ast.ClassDef):
                        continue
                    if child.name.startswith('_'):
                        continue
                    name = f'{prefix}{child.name}'
                    if isinstance(child, ast.ClassDef):
                        role = 'class'
                    else:
                        role = 'meth' if in_class else 'func'
                    for number in _numbers(ast.get_docstring(child) or ''):
                        index[number].add((role, f'{module}.{name}'))
                    if isinstance(child, ast.ClassDef):
                        visit(child, f'{name}.', True)

            visit(tree, '', False)
    return {n: sorted(index[n], key=lambda item: item[1]) for n in sorted(index)}


def _xref(role: str, target: str) -> addnodes.pending_xref:
    short = target.removeprefix('haptic_topology.')
    ref = addnodes.pending_xref('', refdomain='py', reftype=role, reftarget=target,
                                refexplicit=True, refwarn=True)
    ref += nodes.literal(short, short, classes=['xref', 'py', f'py-{role}'])
    return ref


class HapticEquations(Directive):
    """The table: equation number | implemented by."""

    has_content = False

    def run(self) -> list[Any]:
        table = nodes.table(classes=['haptic-equations'])
        group = nodes.tgroup(cols=2)
        table += group
        group += nodes.colspec(colwidth=10)
        group += nodes.colspec(colwidth=90)
        head = nodes.thead()
        group += head
        hrow = nodes.row()
        for title in ('equation', 'implemented or used by'):
            hrow += nodes.entry('', nodes.paragraph(text=title))
        head += hrow
        body = nodes.tbody()
        group += body
        for number, objects in equation_index().items():
            row = nodes.row()
            row += nodes.entry('', nodes.paragraph(text=f'eq. {number}'))
            para = nodes.paragraph()
            for i, (role, target) in enumerate(objects):
                if i:
                    para += nodes.Text(', ')
                para += _xref(role, target)
            row += nodes.entry('', para)
            body += row
        return [table]


def setup(app: Sphinx) -> dict[str, Any]:
    app.add_directive('haptic-equations', HapticEquations)
    return {'version': '1', 'parallel_read_safe': True, 'parallel_write_safe': True}
