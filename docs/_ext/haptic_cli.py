"""Sphinx directive ``haptic-cli``: the subcommands of ``haptic-topology``, from its parser.

Usage (MyST)::

    ```{haptic-cli}
    ```

One row per subcommand of :func:`haptic_topology.cli.build_parser` (name, help, usage), so the
command reference is regenerated from the code at every build.
"""

from __future__ import annotations

import argparse
import os
from typing import Any

from docutils import nodes
from docutils.parsers.rst import Directive
from sphinx.application import Sphinx

from haptic_topology.cli import build_parser


def subcommands() -> dict[str, argparse.ArgumentParser]:
    """Subcommand name -> its parser, in the order ``--help`` lists them."""
    parser = build_parser()
    for action in parser._actions:  # argparse keeps subparsers only here
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    raise RuntimeError('haptic-topology has no subcommands')


class HapticCli(Directive):
    """One heading per subcommand: its one-line help and its ``--help`` text."""

    has_content = False

    def run(self) -> list[Any]:
        os.environ['COLUMNS'] = '100'  # argparse wraps to the terminal; fix the width
        parser = build_parser()
        helps = {}
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                helps = {a.dest: a.help or '' for a in action._choices_actions}
        out: list[Any] = []
        for name, sub in subcommands().items():
            title = f'haptic-topology {name}'
            out.append(nodes.rubric(title, title, ids=[f'cli-{name}']))
            out.append(nodes.paragraph(text=helps.get(name, '')))
            text = sub.format_help()
            out.append(nodes.literal_block(text, text))
        return out


def setup(app: Sphinx) -> dict[str, Any]:
    app.add_directive('haptic-cli', HapticCli)
    return {'version': '1', 'parallel_read_safe': True, 'parallel_write_safe': True}
