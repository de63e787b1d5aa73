"""``make bench``'s mesh section (``bench/mesh_contacts.py``, issue 58): the coal query and the
100 Hz VE update with the robots' collision meshes, or, without example-robot-data, one line
saying why it skipped. Nothing here is timed: the figures are only checked to be there."""

from __future__ import annotations

import importlib.metadata as md
import importlib.util
import sys
from types import ModuleType

from conftest import REPO

BENCH = REPO / 'bench'


def _bench_module(name: str) -> ModuleType:
    spec = importlib.util.spec_from_file_location(f'bench_{name}', BENCH / f'{name}.py')
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def _installed(name: str) -> bool:
    try:
        md.distribution(name)
    except md.PackageNotFoundError:
        return False
    return True


def test_the_mesh_section_measures_or_says_why_not() -> None:
    meshes = _bench_module('mesh_contacts')
    res = meshes.section(n=20, warm=1, timed=2)
    lines = meshes.table(res)
    if not _installed('example-robot-data'):
        assert list(res) == ['skipped'] and 'example-robot-data' in res['skipped']
        assert lines == [f'meshes (coal): skipped: {res["skipped"]}']
        return
    assert list(res) == ['panda_table', 'ur5_table']
    for r in res.values():
        assert r['queries']['mesh_solids'] > 0 and r['queries']['query']['n'] > 0
        for key in ('with_contacts', 'without_contacts'):
            assert set(r[key]['update']) == {'p50_us', 'p99_us', 'n'}
        assert r['with_contacts']['penetrating_candidates'] >= 0
    assert len(lines) == 3 and lines[1].startswith('panda_table')
    assert 'query p50/p99 [us]' in lines[0] and 'VE update p50/p99 [ms]' in lines[0]


def test_make_bench_runs_the_mesh_section() -> None:
    """``bench/run.py`` (``make bench``) measures the section with the others and prints it
    in its table."""
    run = (BENCH / 'run.py').read_text()
    assert "res['meshes'] = mesh_contacts.section()" in run
    assert "lines.extend(mesh_contacts.table(res['meshes']))" in run
