"""One vocabulary module owns topic names and ``/diagnostics`` status names: no other module
of the package spells one as a string literal (a renamed topic or status then changes in one
place, and the nodes, ``run``'s watcher and a bag's index cannot drift apart)."""

from __future__ import annotations

import ast
from pathlib import Path

import haptic_topology
from haptic_topology import vocabulary

PACKAGE = Path(haptic_topology.__file__).parent
OWNED = {name: value for name, value in vars(vocabulary).items()
         if name.startswith(('TOPIC_', 'STATUS_')) and isinstance(value, str)}


def _spelled(path: Path) -> list[str]:
    """``line: literal`` of every string constant in ``path`` equal to an owned name,
    with or without a leading slash."""
    owned = set(OWNED.values()) | {'/' + v for v in OWNED.values()}
    return [f'{node.lineno}: {node.value!r}' for node in ast.walk(ast.parse(path.read_text()))
            if isinstance(node, ast.Constant) and isinstance(node.value, str)
            and node.value in owned]


def test_the_vocabulary_has_the_status_names() -> None:
    assert {'STATUS_DEVICE', 'STATUS_VE', 'STATUS_CONTROLLER', 'STATUS_RECORDER'} <= set(OWNED)


def test_no_module_but_the_vocabulary_spells_a_topic_or_status_name() -> None:
    found = {str(p.relative_to(PACKAGE)): hits for p in sorted(PACKAGE.rglob('*.py'))
             if p.name != 'vocabulary.py' and (hits := _spelled(p))}
    assert found == {}
