"""``launch/haptic_lab.launch.py``, checked without the launch packages (this machine has no
``launch``/``launch_ros``): the file is parsed, never imported. Every executable it starts is
a console script of setup.py, every parameter file it names exists and is installed, every
``LaunchConfiguration`` is declared (and every argument used), it declares scenario, mode,
layout and params_file, its layouts and choices are ``haptic-topology run``'s, the ROS
arguments it passes are accepted by the nodes' own checks with the params file first, it uses
only names that exist in Jazzy's launch/launch_ros, and setup.py installs it. The last test
breaks names in a copy of the file and checks that each check then fails."""

from __future__ import annotations

import argparse
import ast
import runpy
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import setuptools

from haptic_topology.bringup import run as bringup
from haptic_topology.config.node_params import KNOWN
from haptic_topology.config.params import check_overrides, check_params_file, params_files
from haptic_topology.errors import ConfigError

ROOT = Path(__file__).resolve().parents[2]
LAUNCH = ROOT / 'launch' / 'haptic_lab.launch.py'
PACKAGE = 'haptic_topology'

#: Names the launch file may import, as they exist in ROS 2 Jazzy (ros2/launch 3.4,
#: ros2/launch_ros 0.26): ``launch.LaunchDescription``, ``launch.actions.*``,
#: ``launch.substitutions.*``, ``launch.launch_context.LaunchContext``,
#: ``launch_ros.actions.Node``, ``launch_ros.substitutions.FindPackageShare``.
JAZZY_NAMES = {
    'launch': {'LaunchDescription', 'LaunchContext'},
    'launch.actions': {'DeclareLaunchArgument', 'OpaqueFunction', 'GroupAction', 'LogInfo',
                       'SetEnvironmentVariable', 'Shutdown', 'TimerAction',
                       'RegisterEventHandler', 'ExecuteProcess', 'EmitEvent'},
    'launch.substitutions': {'LaunchConfiguration', 'PathJoinSubstitution', 'TextSubstitution',
                             'PythonExpression', 'EnvironmentVariable'},
    'launch.launch_context': {'LaunchContext'},
    'launch.conditions': {'IfCondition', 'UnlessCondition', 'LaunchConfigurationEquals'},
    'launch_ros.actions': {'Node', 'LifecycleNode', 'ComposableNodeContainer'},
    'launch_ros.substitutions': {'FindPackageShare', 'FindPackagePrefix'},
}
#: Keyword arguments of ``launch_ros.actions.Node`` in Jazzy (its own, then those of
#: ``launch.actions.ExecuteProcess`` it forwards) that the file may use.
NODE_KWARGS = {'executable', 'package', 'name', 'namespace', 'exec_name', 'parameters',
               'remappings', 'ros_arguments', 'arguments', 'output', 'emulate_tty', 'respawn',
               'respawn_delay', 'sigterm_timeout', 'sigkill_timeout', 'additional_env',
               'condition', 'cwd'}


# -- helpers: each check works on a parsed launch file, so a broken copy can be checked -----
def _tree(path: Path = LAUNCH) -> ast.Module:
    return ast.parse(path.read_text(encoding='utf-8'), filename=str(path))


def _calls(tree: ast.AST, name: str) -> list[ast.Call]:
    return [n for n in ast.walk(tree) if isinstance(n, ast.Call)
            and isinstance(n.func, ast.Name) and n.func.id == name]


def _kw(call: ast.Call, name: str) -> ast.expr | None:
    return next((k.value for k in call.keywords if k.arg == name), None)


def _module_constant(tree: ast.Module, name: str) -> Any:
    for node in tree.body:
        if (isinstance(node, ast.Assign) and len(node.targets) == 1
                and isinstance(node.targets[0], ast.Name) and node.targets[0].id == name):
            return ast.literal_eval(node.value)
    raise AssertionError(f'{LAUNCH.name}: no module-level {name} = <literal>')


def _string_arg(call: ast.Call, what: str) -> str:
    assert call.args and isinstance(call.args[0], ast.Constant) \
        and isinstance(call.args[0].value, str), \
        f'line {call.lineno}: {what} must name its argument as a string literal'
    return call.args[0].value


def _setup_kwargs(monkeypatch: pytest.MonkeyPatch) -> dict[str, Any]:
    """The keyword arguments setup.py passes to ``setuptools.setup`` (globs from the repo)."""
    captured: dict[str, Any] = {}
    monkeypatch.setattr(setuptools, 'setup', lambda **kw: captured.update(kw))
    monkeypatch.chdir(ROOT)
    runpy.run_path(str(ROOT / 'setup.py'))
    return captured


def _console_scripts(kwargs: dict[str, Any]) -> set[str]:
    return {line.split('=')[0].strip() for line in kwargs['entry_points']['console_scripts']}


def _installed(kwargs: dict[str, Any]) -> dict[str, str]:
    """Repo-relative file -> the share directory setup.py installs it to."""
    return {src: dest for dest, files in kwargs['data_files'] for src in files}


def check_executables(tree: ast.Module, scripts: set[str]) -> set[str]:
    """Every ``Node(executable=...)`` is a console script; returns the executables. An
    executable that is not a string literal must be the loop variable over ``LAYOUTS[...]``
    (whose values are then checked)."""
    layouts = _module_constant(tree, 'LAYOUTS')
    loops: dict[str, ast.expr] = {}
    for n in ast.walk(tree):
        gens = n.generators if isinstance(n, (ast.ListComp, ast.GeneratorExp)) else []
        for g in gens:
            if isinstance(g.target, ast.Name):
                loops[g.target.id] = g.iter
        if isinstance(n, ast.For) and isinstance(n.target, ast.Name):
            loops[n.target.id] = n.iter
    found: set[str] = set()
    nodes = _calls(tree, 'Node')
    assert nodes, 'no Node(...) in the launch file'
    for call in nodes:
        package = _kw(call, 'package')
        assert isinstance(package, ast.Name) and package.id == 'PACKAGE' \
            and _module_constant(tree, 'PACKAGE') == PACKAGE, \
            f'line {call.lineno}: package= must be PACKAGE = {PACKAGE!r}'
        exe = _kw(call, 'executable')
        if isinstance(exe, ast.Constant) and isinstance(exe.value, str):
            found.add(exe.value)
        elif isinstance(exe, ast.Name) and isinstance(loops.get(exe.id), ast.Subscript) \
                and isinstance(loops[exe.id].value, ast.Name) \
                and loops[exe.id].value.id == 'LAYOUTS':
            found.update(name for names in layouts.values() for name in names)
        else:
            raise AssertionError(f'line {call.lineno}: cannot check executable= statically')
    missing = found - scripts
    assert not missing, f'executables that are no console script of setup.py: {missing}'
    return found


def check_launch_configurations(tree: ast.Module) -> set[str]:
    """Every ``LaunchConfiguration`` is declared and every declared argument is used;
    returns the declared names."""
    declared = [_string_arg(c, 'DeclareLaunchArgument') for c in
                _calls(tree, 'DeclareLaunchArgument')]
    used = {_string_arg(c, 'LaunchConfiguration') for c in _calls(tree, 'LaunchConfiguration')}
    assert len(declared) == len(set(declared)), f'declared twice: {declared}'
    assert used <= set(declared), f'used but not declared: {used - set(declared)}'
    assert set(declared) <= used, f'declared but never used: {set(declared) - used}'
    return set(declared)


def check_parameter_files(tree: ast.Module, installed: dict[str, str]) -> list[str]:
    """Every ``PathJoinSubstitution([FindPackageShare(PACKAGE), ...])`` names a file of the
    repo that setup.py installs to that share path, and it is a valid params file of the
    graph's nodes; returns the repo-relative paths."""
    paths = []
    for call in _calls(tree, 'PathJoinSubstitution'):
        parts = call.args[0]
        assert isinstance(parts, ast.List) and parts.elts
        head, *rest = parts.elts
        if not (isinstance(head, ast.Call) and isinstance(head.func, ast.Name)
                and head.func.id == 'FindPackageShare'):
            continue
        assert all(isinstance(p, ast.Constant) and isinstance(p.value, str) for p in rest), \
            f'line {call.lineno}: share path parts must be string literals'
        rel = '/'.join(str(p.value) for p in rest if isinstance(p, ast.Constant))
        assert (ROOT / rel).is_file(), f'{rel}: no such file in the repository'
        dest = installed.get(rel)
        assert dest == f'share/{PACKAGE}/{Path(rel).parent}', \
            f'{rel}: not installed by setup.py to share/{PACKAGE}/{Path(rel).parent} ({dest})'
        if rel.endswith('.yaml'):
            check_params_file(ROOT / rel, KNOWN)
        paths.append(rel)
    assert paths, 'no parameter file of the package share found'
    return paths


def _ros_arguments_function(tree: ast.Module) -> Callable[..., list[str]]:
    """The launch file's ``ros_arguments`` (pure: no launch import), compiled on its own."""
    fn = next(n for n in tree.body if isinstance(n, ast.FunctionDef)
              and n.name == 'ros_arguments')
    module = ast.Module(body=[fn], type_ignores=[])
    namespace: dict[str, Any] = {}
    exec(compile(module, str(LAUNCH), 'exec'), namespace)
    function: Callable[..., list[str]] = namespace['ros_arguments']
    return function


# -- the tests -------------------------------------------------------------------------------
def test_setup_installs_the_launch_file(monkeypatch: pytest.MonkeyPatch) -> None:
    installed = _installed(_setup_kwargs(monkeypatch))
    assert installed.get('launch/haptic_lab.launch.py') == f'share/{PACKAGE}/launch'


def test_every_executable_is_a_console_script(monkeypatch: pytest.MonkeyPatch) -> None:
    scripts = _console_scripts(_setup_kwargs(monkeypatch))
    found = check_executables(_tree(), scripts)
    assert found == {'recorder', 've_sim', 'lmi_controller', 'device_driver', 'composed'}


def test_arguments_are_declared_used_and_cover_the_run_options() -> None:
    tree = _tree()
    declared = check_launch_configurations(tree)
    assert {'scenario', 'mode', 'layout', 'params_file'} <= declared
    choices = {_string_arg(c, 'DeclareLaunchArgument'): ast.unparse(_kw(c, 'choices'))
               for c in _calls(tree, 'DeclareLaunchArgument') if _kw(c, 'choices') is not None}
    assert choices == {'mode': 'list(MODES)', 'layout': 'list(LAYOUTS)',
                       'clock': 'list(CLOCKS)'}
    # The same graph as `haptic-topology run`: its layouts start the same processes (node
    # modules there, console scripts here), its modes and clocks are the choices here.
    assert _module_constant(tree, 'LAYOUTS') == bringup.LAYOUTS
    assert tuple(_module_constant(tree, 'CLOCKS')) == bringup.CLOCKS
    parser = argparse.ArgumentParser()
    bringup.add_arguments(parser)
    run_modes = next(a.choices for a in parser._actions if a.dest == 'mode')
    assert set(_module_constant(tree, 'MODES')) == {'', *run_modes}


def test_parameter_files_exist_and_are_installed(monkeypatch: pytest.MonkeyPatch) -> None:
    paths = check_parameter_files(_tree(), _installed(_setup_kwargs(monkeypatch)))
    assert paths == ['config/haptic_topology.yaml']


@pytest.mark.parametrize(('layout', 'clock', 'mode', 'output', 'backend'), [
    ('hosted', 'wall', '', '', ''),
    ('separate', 'lockstep', 'penalty', 'bags/x', 'fake_backend:CircleBackend'),
    ('composed', 'wall', 'acceleration_only', '', 'sim_maglev'),
    ('thread', 'lockstep', '', '', ''),
])
def test_ros_arguments_pass_the_nodes_checks_params_file_first(
        layout: str, clock: str, mode: str, output: str, backend: str) -> None:
    """What every process gets is accepted by the nodes' own checks (params file and every
    ``-p`` name, for all four nodes), the params file comes before every override (the last
    assignment wins), and the layout, clock and options show up as in ``haptic-topology
    run``. The nodes get it through ``ros_arguments=``, never ``parameters=`` (which would put
    the file after the overrides) nor ``name=`` (which would rename the hosted controller)."""
    tree = _tree()
    params = str(ROOT / 'config' / 'haptic_topology.yaml')
    args = _ros_arguments_function(tree)(params, 'fig6', mode, layout, clock, 2.5, output,
                                         backend)
    assert params_files(args) == [params] and args[:2] == ['--params-file', params]
    check_params_file(params, KNOWN)
    check_overrides(args, KNOWN)
    overrides = [args[i + 1] for i, a in enumerate(args) if a == '-p']
    assert 'scenario:=fig6' in overrides and f'clock:={clock}' in overrides
    assert 'device_driver:run_duration:=2.5' in overrides
    assert 'device_driver:min_subscribers:=2' in overrides
    host = 'false' if layout == 'separate' else 'true'
    assert f'device_driver:host_controller:={host}' in overrides
    assert ('lmi_controller:use_sim_time:=true' in overrides) == (clock == 'lockstep')
    assert ('ve_sim:use_sim_time:=true' in overrides) == (clock == 'lockstep')
    assert (f'lmi_controller:mode:={mode}' in overrides) == bool(mode)
    assert (f'recorder:output:={output}' in overrides) == bool(output)
    assert (f'device_driver:backend:={backend}' in overrides) == bool(backend)
    assert ('device_driver:loop_process:=false' in overrides) == (layout == 'thread')
    for call in _calls(tree, 'Node'):
        kwargs = {k.arg for k in call.keywords}
        assert kwargs <= NODE_KWARGS, f'not a Jazzy Node argument: {kwargs - NODE_KWARGS}'
        assert 'ros_arguments' in kwargs and not kwargs & {'parameters', 'name'}


def test_imports_exist_in_jazzy_launch() -> None:
    tree = _tree()
    imports = [n for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)
               and n.module and n.module.split('.')[0] in ('launch', 'launch_ros')]
    assert {n.module for n in imports} >= {'launch', 'launch_ros.actions'}
    for n in imports:
        names = {a.name for a in n.names}
        assert n.module in JAZZY_NAMES, f'{n.module}: not a module checked here'
        assert names <= JAZZY_NAMES[n.module], \
            f'{n.module}: {names - JAZZY_NAMES[n.module]} not in Jazzy'
    assert any(f.name == 'generate_launch_description' for f in tree.body
               if isinstance(f, ast.FunctionDef))


@pytest.mark.parametrize(('old', 'new', 'check', 'expect'), [
    ("'device_driver'),\n    'separate'", "'device_drivr'),\n    'separate'", 'executables',
     "no console script of setup.py: {'device_drivr'}"),
    ("LaunchConfiguration('mode')", "LaunchConfiguration('moed')", 'configurations',
     "used but not declared: {'moed'}"),
    ("DeclareLaunchArgument('backend'", "DeclareLaunchArgument('backends'", 'configurations',
     "used but not declared: {'backend'}"),
    ("'config', 'haptic_topology.yaml'", "'config', 'haptic_topolgy.yaml'", 'files',
     'config/haptic_topolgy.yaml: no such file in the repository'),
    ("'config', 'haptic_topology.yaml'", "'config', 'linkages', 'table1_planar3.yaml'",
     'files', 'table1_planar3.yaml: linkage: unknown node'),
])
def test_the_checks_fail_on_a_wrong_name(monkeypatch: pytest.MonkeyPatch, tmp_path: Path,
                                         old: str, new: str, check: str, expect: str) -> None:
    """Each check rejects a copy of the launch file with one name broken (an executable
    that is no console script, an undeclared configuration or unused argument, a params file
    that does not exist, or one that is no params file of the nodes)."""
    text = LAUNCH.read_text(encoding='utf-8')
    assert text.count(old) == 1
    broken = tmp_path / LAUNCH.name
    broken.write_text(text.replace(old, new), encoding='utf-8')
    kwargs = _setup_kwargs(monkeypatch)
    run_check: dict[str, Callable[[ast.Module], object]] = {
        'executables': lambda t: check_executables(t, _console_scripts(kwargs)),
        'configurations': check_launch_configurations,
        'files': lambda t: check_parameter_files(t, _installed(kwargs)),
    }
    for name, fn in run_check.items():
        fn(_tree())                            # the real file passes every check
        if name != check:
            continue
        with pytest.raises((AssertionError, ConfigError)) as err:
            fn(_tree(broken))
        assert expect in str(err.value)
