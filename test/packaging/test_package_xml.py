"""``package.xml`` (and ``msg_schemas/package.xml``) against the code: every module that
``haptic_topology/`` and ``launch/`` import, beyond the standard library and the package itself,
is declared with its rosdep key, and every declared key is used; the test suite's imports and
pytest plugins are declared as test dependencies; maintainer and license agree with setup.py
and the LICENSE file; the interface package depends on every package its fields use."""

from __future__ import annotations

import ast
import hashlib
import re
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
from catkin_pkg.package import parse_package

ROOT = Path(__file__).resolve().parents[2]

#: Top-level import name -> rosdep key. Keys checked against rosdistro: rosdep/python.yaml
#: (python3-numpy, python3-yaml, python3-matplotlib, python3-setuptools,
#: python3-pytest, python3-pytest-timeout, python3-pytest-xdist, python3-hypothesis,
#: python3-catkin-pkg-modules,
#: python3-rosbags-pip, mcap-ros2-support) and the Jazzy distribution (ROS packages,
#: pinocchio, coal). ``mcap`` and ``zstandard`` have no key of their own: the
#: mcap-ros2-support key installs them (pip: mcap-ros2-support -> mcap -> zstandard).
#: An import of a ROS interface package (``*_msgs``, ``*_interfaces``, ``*_srvs``) maps to
#: the package of that name without being listed here.
IMPORT_KEYS = {
    'rclpy': 'rclpy',
    'ament_index_python': 'ament_index_python',
    'launch': 'launch',
    'launch_ros': 'launch_ros',
    'numpy': 'python3-numpy',
    'scipy': 'python3-scipy',
    'yaml': 'python3-yaml',
    'matplotlib': 'python3-matplotlib',
    'pinocchio': 'pinocchio',
    'coal': 'coal',
    'rosbags': 'python3-rosbags-pip',
    'mcap': 'mcap-ros2-support',
    'mcap_ros2': 'mcap-ros2-support',
    'zstandard': 'mcap-ros2-support',
    'setuptools': 'python3-setuptools',
    'pytest': 'python3-pytest',
    'hypothesis': 'python3-hypothesis',
    'catkin_pkg': 'python3-catkin-pkg-modules',
    'websockets': 'python3-websockets',    # test/graph/test_foxglove.py's client
}
#: Imported modules that rosdistro has no key for on Jazzy's Ubuntu (python.yaml checked): not
#: declared, but package.xml must name their PyPI distribution in a comment.
NO_ROSDEP_KEY = {
    'foxglove': 'foxglove-sdk',     # the optional foxglove_bridge node
    'numba': 'numba (PyPI',         # python3-numba: Debian, Ubuntu bionic/focal only
    'pyarrow': 'pyarrow (PyPI',     # Apache Arrow: not in Ubuntu noble's archive
    'forcedimension_core': 'forcedimension-core (PyPI',     # backend forcedimension
    'pyOpenHaptics': 'pyOpenHaptics (PyPI',     # backend openhaptics
}
#: Declared dependencies that no import shows, and where they are used.
NOT_IMPORTED: dict[str, str] = {}
#: Licences of third-party files shipped in the package (REP 149: one <license file=...> each).
SHIPPED_LICENSES = {
    'config/robots/example-robot-data/LICENSE': ('BSD-2-Clause', 'BSD 2-Clause License'),
    'config/robots/example-robot-data/robots/panda_description/LICENSE': (
        'Apache-2.0', 'Apache License'),
    'config/robots/example-robot-data/robots/ur_description/README.md': ('BSD', 'license: BSD'),
}
FIRST_PARTY = {'haptic_topology'}
PLACEHOLDERS = ('dev@haptic.local', 'haptic-dev', 'todo', 'example.com')
#: SHA-256 of the Apache License 2.0 text as published at apache.org (LICENSE-2.0.txt).
APACHE_2_SHA256 = 'cfc7749b96f63bd31c3c42b5c471bf756814053e847c10f3eb003417bc523d30'


def _manifest(path: Path) -> ET.Element:
    return ET.parse(path).getroot()


def _deps(root: ET.Element, *tags: str) -> set[str]:
    return {(e.text or '').strip() for tag in tags for e in root.iter(tag)}


def _imports(paths: list[Path]) -> dict[str, set[str]]:
    """Top-level module -> the files importing it (absolute imports only)."""
    found: dict[str, set[str]] = {}
    for p in paths:
        for n in ast.walk(ast.parse(p.read_text(encoding='utf-8'), filename=str(p))):
            names = ([a.name for a in n.names] if isinstance(n, ast.Import)
                     else [n.module] if isinstance(n, ast.ImportFrom) and n.level == 0
                     and n.module else [])
            for name in names:
                found.setdefault(name.split('.')[0], set()).add(str(p.relative_to(ROOT)))
    return found


def _third_party(imports: dict[str, set[str]], local: set[str]) -> dict[str, set[str]]:
    return {m: f for m, f in imports.items()
            if m not in sys.stdlib_module_names and m not in FIRST_PARTY and m not in local
            and m != '__future__'}


def _key(module: str, where: set[str]) -> str | None:
    """The rosdep key of ``module`` (None: it has none, see NO_ROSDEP_KEY)."""
    if module in NO_ROSDEP_KEY:
        return None
    if module in IMPORT_KEYS:
        return IMPORT_KEYS[module]
    if module.endswith(('_msgs', '_interfaces', '_srvs')):
        return module
    raise AssertionError(f'{module} (imported in {sorted(where)}): add its rosdep key to '
                         'IMPORT_KEYS and to package.xml')


def _package_sources() -> list[Path]:
    return sorted((ROOT / 'haptic_topology').rglob('*.py')) + sorted(
        (ROOT / 'launch').glob('*.py'))


def test_every_import_is_declared_with_its_rosdep_key() -> None:
    """A module that the package (or its launch file) imports at run time must be an
    exec_depend (or depend) of package.xml under its rosdep key."""
    declared = _deps(_manifest(ROOT / 'package.xml'), 'exec_depend', 'depend')
    text = (ROOT / 'package.xml').read_text(encoding='utf-8')
    missing = {}
    for module, where in _third_party(_imports(_package_sources()), set()).items():
        key = _key(module, where)
        if key is None:
            assert NO_ROSDEP_KEY[module] in text, \
                f'{module}: package.xml must say that {NO_ROSDEP_KEY[module]} has no rosdep key'
        elif key not in declared:
            missing[module] = (key, sorted(where)[:3])
    assert not missing, f'imported but not declared in package.xml (module: key, files): {missing}'


def test_every_declared_dependency_is_used() -> None:
    """Every exec_depend comes from an import of the package or launch file (through its
    key) or is listed in NOT_IMPORTED with a use that exists; the buildtool dependency is what
    setup.py imports."""
    root = _manifest(ROOT / 'package.xml')
    modules = _third_party(_imports(_package_sources()), set())
    keys = {_key(m, w) for m, w in modules.items()}
    unused = _deps(root, 'exec_depend', 'depend') - keys - set(NOT_IMPORTED)
    assert not unused, f'declared in package.xml but never imported: {unused}'
    config = '\n'.join(p.read_text(encoding='utf-8') for p in (ROOT / 'config').rglob('*.yaml'))
    for dep, use in NOT_IMPORTED.items():
        assert dep in _deps(root, 'exec_depend'), dep
        assert use in config, f'{dep}: declared for {use!r}, which config/ no longer uses'
    setup_keys = {_key(m, w) for m, w in
                  _third_party(_imports([ROOT / 'setup.py']), set()).items()}
    assert _deps(root, 'buildtool_depend', 'build_depend') == setup_keys == {
        'python3-setuptools'}


def test_test_dependencies_are_declared() -> None:
    """The test suite's imports are declared (as exec or test dependencies), and so are the
    pytest plugins the configuration relies on (``-n``: xdist, ``timeout``: pytest-timeout)."""
    root = _manifest(ROOT / 'package.xml')
    declared = _deps(root, 'exec_depend', 'depend', 'test_depend', 'buildtool_depend')
    tests = sorted(p for p in (ROOT / 'test').rglob('*.py') if 'node_modules' not in p.parts)
    # the tests' helpers and the docs' Sphinx extensions, which test/docs imports
    local = {p.stem for p in [*tests, *(ROOT / 'docs' / '_ext').glob('*.py')]}
    missing = {m: _key(m, w) for m, w in _third_party(_imports(tests), local).items()
               if _key(m, w) not in declared | {None}}
    assert not missing, f'imported by the tests but not declared: {missing}'
    pyproject = (ROOT / 'pyproject.toml').read_text(encoding='utf-8')
    test_deps = _deps(root, 'test_depend')
    if re.search(r'^addopts = .*-n \d', pyproject, re.M):
        assert 'python3-pytest-xdist' in test_deps
    if re.search(r'^timeout = \d', pyproject, re.M):
        assert 'python3-pytest-timeout' in test_deps
    assert 'python3-pytest' in test_deps


@pytest.mark.parametrize('manifest', ['package.xml', 'msg_schemas/package.xml'])
def test_maintainer_and_license_agree_with_setup_py(manifest: str) -> None:
    """Both manifests name the same maintainer as setup.py (not a placeholder) and the license
    setup.py declares, which is the license of the LICENSE file: the Apache License 2.0 text,
    verbatim."""
    root = _manifest(ROOT / manifest)
    setup = {k.arg: ast.literal_eval(k.value) for n in ast.walk(ast.parse(
        (ROOT / 'setup.py').read_text(encoding='utf-8'))) if isinstance(n, ast.Call)
        and isinstance(n.func, ast.Name) and n.func.id == 'setup' for k in n.keywords
        if k.arg in ('maintainer', 'maintainer_email', 'license')}
    (maintainer,) = root.iter('maintainer')
    assert (maintainer.text, maintainer.get('email')) == (setup['maintainer'],
                                                          setup['maintainer_email'])
    assert re.fullmatch(r'[^@\s]+@[^@\s]+\.[a-z]+', setup['maintainer_email'])
    for text in (setup['maintainer'], setup['maintainer_email']):
        assert not any(p in text.lower() for p in PLACEHOLDERS), text
    own = [e.text for e in root.iter('license') if e.get('file') is None]
    assert own == [setup['license']] == ['Apache-2.0']
    shipped = {e.get('file'): e.text for e in root.iter('license') if e.get('file')}
    assert shipped == ({f: spdx for f, (spdx, _) in SHIPPED_LICENSES.items()}
                       if manifest == 'package.xml' else {})
    for f, (_, words) in SHIPPED_LICENSES.items():
        assert words in (ROOT / f).read_text(encoding='utf-8'), f'{f} is not its licence'
    license_text = (ROOT / 'LICENSE').read_bytes()
    assert hashlib.sha256(license_text).hexdigest() == APACHE_2_SHA256
    assert b'Apache License\n                           Version 2.0, January 2004' in \
        license_text


def test_interface_package_depends_on_what_its_fields_use() -> None:
    """Every package whose types the .msg files use is a depend of haptic_topology_msgs, and
    the rosidl dependencies of an interface package are there."""
    msg_dir = ROOT / 'msg_schemas'
    root = _manifest(msg_dir / 'package.xml')
    used = set()
    for msg in (msg_dir / 'msg').glob('*.msg'):
        for line in msg.read_text(encoding='utf-8').splitlines():
            field = line.split('#')[0].split()
            if field and '/' in field[0]:
                used.add(field[0].split('/')[0])
    assert used and used <= _deps(root, 'depend', 'build_depend')
    assert 'rosidl_default_generators' in _deps(root, 'buildtool_depend')
    assert 'rosidl_default_runtime' in _deps(root, 'exec_depend')
    assert [e.text for e in root.iter('member_of_group')] == ['rosidl_interface_packages']
    cmake = (msg_dir / 'CMakeLists.txt').read_text(encoding='utf-8')
    for pkg in used:
        assert f'find_package({pkg} REQUIRED)' in cmake


@pytest.mark.parametrize(('directory', 'name'), [('.', 'haptic_topology'),
                                                  ('msg_schemas', 'haptic_topology_msgs')])
def test_manifests_are_valid_format_3(directory: str, name: str) -> None:
    """catkin_pkg (the parser of colcon, rosdep and bloom) reads and validates both
    manifests (format 3, a maintainer with an email, a license, no dependency declared twice
    in one kind), with the expected name and setup.py's version."""
    pkg = parse_package(ROOT / directory)
    pkg.validate()
    assert (pkg.name, pkg.package_format) == (name, 3)
    assert pkg.version == next(k.value.value for n in ast.walk(ast.parse(
        (ROOT / 'setup.py').read_text(encoding='utf-8'))) if isinstance(n, ast.Call)
        for k in n.keywords if k.arg == 'version' and isinstance(k.value, ast.Constant))
