"""``make bench``'s mesh section (``bench/mesh_contacts.py``, issue 58): the coal query and the
100 Hz VE update with the robots' collision meshes and their self-collisions, on a default
install. Nothing here is timed: the figures are only checked to be there."""

from __future__ import annotations

import importlib.metadata as md
import importlib.util
import sys
from types import ModuleType

import pytest
from conftest import REPO

BENCH = REPO / 'bench'


def _bench_module(name: str) -> ModuleType:
    spec = importlib.util.spec_from_file_location(f'bench_{name}', BENCH / f'{name}.py')
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def test_the_mesh_section_measures_on_a_default_install(monkeypatch: pytest.MonkeyPatch
                                                        ) -> None:
    """Without example-robot-data (the optional extra: here hidden from the package metadata)
    the section measures the shipped robots: the coal query, and the VE update with the
    contacts, with the self-collisions too (the pairs they check) and without contacts."""
    real = md.distribution

    def distribution(name: str) -> md.Distribution:
        if name == 'example-robot-data':
            raise md.PackageNotFoundError(name)
        return real(name)

    monkeypatch.setattr(md, 'distribution', distribution)
    meshes = _bench_module('mesh_contacts')
    res = meshes.section(n=20, warm=1, timed=2)
    lines = meshes.table(res)
    assert list(res) == ['panda_table', 'ur5_table']
    assert [r['pairs'] for r in res.values()] == [32, 11]
    for r in res.values():
        assert r['queries']['mesh_solids'] > 0 and r['queries']['query']['n'] > 0
        for key in ('with_contacts', 'with_self', 'without_contacts'):
            assert set(r[key]['update']) == {'p50_us', 'p99_us', 'n'}
        for key in ('with_contacts', 'with_self'):
            assert set(r[key]['torques_call']) == {'p50_us', 'p99_us', 'n'}
            assert r[key]['penetrating_candidates'] >= 0
    assert len(lines) == 3 and lines[1].startswith('panda_table')
    assert lines[2].startswith('ur5_table') and '(11)' in lines[2]
    assert 'query p50/p99 [us]' in lines[0] and 'VE update p50/p99 [ms]' in lines[0]
    assert '+ self-collisions (pairs)' in lines[0]


def test_make_bench_runs_the_mesh_section() -> None:
    """``bench/run.py`` (``make bench``) measures the section with the others and prints it
    in its table."""
    run = (BENCH / 'run.py').read_text()
    assert "res['meshes'] = mesh_contacts.section()" in run
    assert "lines.extend(mesh_contacts.table(res['meshes']))" in run
