"""Sphinx directive ``haptic-params``: a node's parameter table, generated from its settings class.

Usage (MyST)::

    ```{haptic-params} device_driver
    ```

The argument is a node name of :data:`haptic_topology.config.node_params.KNOWN`; the rows are
:func:`haptic_topology.config.settings.param_specs` of the node's settings class, so the page
is regenerated from the code at every build and cannot drift from what the node declares.
"""

from __future__ import annotations

from typing import Any

from docutils import nodes
from docutils.parsers.rst import Directive
from sphinx.application import Sphinx

from haptic_topology.config.node_params import KNOWN
from haptic_topology.config.params import ParamSpec

HEADER = ('parameter', 'type', 'default', 'range / choices', 'live', 'description')


def _number(value: float) -> str:
    return f'{value:g}'


def row_cells(spec: ParamSpec) -> tuple[str, ...]:
    """The table row of one parameter (the same text the tests compare against)."""
    if spec.choices:
        allowed = ', '.join(spec.choices)
    elif spec.lo is not None or spec.hi is not None:
        lo = '-inf' if spec.lo is None else _number(spec.lo)
        hi = 'inf' if spec.hi is None else _number(spec.hi)
        allowed = f'[{lo}, {hi}]'
    else:
        allowed = ''
    default = repr(spec.default) if isinstance(spec.default, str) else str(spec.default)
    if isinstance(spec.default, bool):
        default = 'true' if spec.default else 'false'
    return (spec.name, spec.kind(), default, allowed, 'no' if spec.read_only else 'yes',
            spec.description)


def _cell(text: str, literal: bool) -> nodes.entry:
    entry = nodes.entry()
    para = nodes.paragraph()
    para += nodes.literal(text, text) if literal and text else nodes.Text(text)
    entry += para
    return entry


def _table(rows: list[tuple[str, ...]], widths: tuple[int, ...]) -> nodes.table:
    table = nodes.table(classes=['haptic-params'])
    group = nodes.tgroup(cols=len(HEADER))
    table += group
    for width in widths:
        group += nodes.colspec(colwidth=width)
    head = nodes.thead()
    group += head
    hrow = nodes.row()
    for title in HEADER:
        hrow += _cell(title, literal=False)
    head += hrow
    body = nodes.tbody()
    group += body
    for cells in rows:
        row = nodes.row()
        for i, text in enumerate(cells):
            row += _cell(text, literal=i in (0, 2))
        body += row
    return table


class HapticParams(Directive):
    """``.. haptic-params:: NODE``: the parameter table of NODE."""

    required_arguments = 1
    has_content = False

    def run(self) -> list[Any]:
        node_name = self.arguments[0]
        specs = KNOWN.get(node_name)
        if specs is None:
            known = ', '.join(sorted(n for n, s in KNOWN.items() if s is not None))
            raise self.error(f'haptic-params: unknown node {node_name!r} (expected one of: '
                             f'{known})')
        rows = [row_cells(spec) for spec in specs.values()]
        return [_table(rows, (14, 8, 10, 12, 4, 52))]


def setup(app: Sphinx) -> dict[str, Any]:
    app.add_directive('haptic-params', HapticParams)
    return {'version': '1', 'parallel_read_safe': True, 'parallel_write_safe': True}
