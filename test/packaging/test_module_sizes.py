"""Module sizes (issue 25 item 7): every node module (ROS I/O only) stays within 200 code lines,
and a module of more than 500 lines says at its top why it is one module."""

from __future__ import annotations

import ast
import io
import tokenize
from pathlib import Path

from conftest import REPO

PACKAGE = REPO / 'haptic_topology'
NODE_CODE_LINES = 200
LONG_MODULE = 500
#: The words a long module's docstring starts its reason with.
REASON = 'lines on purpose:'


def code_lines(path: Path) -> int:
    """Lines holding code: no blank line, comment or docstring."""
    src = path.read_text()
    docs: set[int] = set()
    for node in ast.walk(ast.parse(src)):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            first = node.body[0] if node.body else None
            if (isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant)
                    and isinstance(first.value.value, str)):
                docs.update(range(first.lineno, (first.end_lineno or first.lineno) + 1))
    skip = {tokenize.COMMENT, tokenize.NL, tokenize.NEWLINE, tokenize.INDENT, tokenize.DEDENT,
            tokenize.ENCODING, tokenize.ENDMARKER}
    lines: set[int] = set()
    for tok in tokenize.generate_tokens(io.StringIO(src).readline):
        if tok.type not in skip:
            lines.update(n for n in range(tok.start[0], tok.end[0] + 1) if n not in docs)
    return len(lines)


def test_code_lines_counts_code_only(tmp_path: Path) -> None:
    f = tmp_path / 'm.py'
    f.write_text('"""Doc\n\nmore doc."""\n\n# a comment\nx = (1,\n     2)\n\n\ndef g() -> int:\n'
                 '    """Doc."""\n    return x[0]\n')
    assert code_lines(f) == 4


def test_node_modules_are_thin() -> None:
    sizes = {p.name: code_lines(p) for p in sorted((PACKAGE / 'nodes').glob('*.py'))}
    assert len(sizes) > 10
    assert {n: s for n, s in sizes.items() if s > NODE_CODE_LINES} == {}


def test_long_modules_say_why() -> None:
    unexplained = []
    for path in sorted(PACKAGE.rglob('*.py')):
        if len(path.read_text().splitlines()) > LONG_MODULE:
            doc = ast.get_docstring(ast.parse(path.read_text())) or ''
            if REASON not in ' '.join(doc.split()[:60]):
                unexplained.append(str(path.relative_to(REPO)))
    assert unexplained == []
