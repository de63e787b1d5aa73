"""The backend conformance checks (``backend_conformance.py``) for the backends that run in the
driver's process without ROS: the simulated maglev (built in) and the example third-party
backend of ``examples/my_device_backend``, installed here as a distribution of its own (pip,
into a temporary directory) and found through the entry point group
``haptic_topology.device_backends``, as a user's package would be. The ``ros_topics`` backend
goes through the same checks in ``test_topic_backend.py`` (against a device process)."""

from __future__ import annotations

import importlib
import importlib.metadata as md
import shutil
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from backend_conformance import (
    Applied,
    Bench,
    Subject,
    check_clamping,
    check_lifecycle,
    check_nonfinite,
    check_watchdog,
)

from haptic_topology.device.backend import (
    ENTRY_POINT_GROUP,
    BackendConfig,
    backend_class,
    create_backend,
)
from haptic_topology.errors import DeviceError
from haptic_topology.sim.lockstep import initial_device_pose
from haptic_topology.sim.scenario import load_scenario

EXAMPLE = Path(__file__).resolve().parents[3] / 'examples' / 'my_device_backend'
EXAMPLE_NAME = 'my_spring'


@pytest.fixture(scope='module')
def example_installed(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """``pip install --no-deps --target <tmp>`` of a copy of the example (the build writes
    into its source tree), then the target on ``sys.path``: the entry point comes from the
    installed distribution's metadata, nothing is registered by hand."""
    tmp = tmp_path_factory.mktemp('example')
    src = tmp / 'src'
    shutil.copytree(EXAMPLE, src)
    target = tmp / 'site'
    proc = subprocess.run(
        [sys.executable, '-m', 'pip', 'install', '--quiet', '--no-deps', '--no-index',
         '--no-build-isolation', '--target', str(target), str(src)],
        capture_output=True, text=True, timeout=240)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    sys.path.insert(0, str(target))
    importlib.invalidate_caches()
    try:
        yield target
    finally:
        sys.path.remove(str(target))
        sys.modules.pop('my_device_backend', None)


def test_example_is_found_through_its_entry_point(example_installed: Path) -> None:
    eps = {ep.name: ep for ep in md.entry_points(group=ENTRY_POINT_GROUP)}
    assert eps[EXAMPLE_NAME].value == 'my_device_backend:SpringBackend'
    assert eps[EXAMPLE_NAME].dist is not None
    assert eps[EXAMPLE_NAME].dist.name == 'my-device-backend'
    cls = backend_class(EXAMPLE_NAME)
    module = sys.modules[cls.__module__]
    assert Path(str(module.__file__)).is_relative_to(example_installed)
    assert create_backend(EXAMPLE_NAME).name == EXAMPLE_NAME
    with pytest.raises(DeviceError, match=f'expected one of .*{EXAMPLE_NAME}'):
        backend_class('no_such_backend')


def test_example_refuses_bad_options_naming_the_field(example_installed: Path) -> None:
    sc = load_scenario('fig8')
    be = create_backend(EXAMPLE_NAME)
    for options, text in (({'stiffness': -1.0}, 'backend_options.stiffness: expected a '
                           'number >= 0, got -1.0'),
                          ({'mass': 'heavy'}, "backend_options.mass: expected a number > 0, "
                           "got 'heavy'"),
                          ({'port': 3}, "unknown option 'port'")):
        with pytest.raises(DeviceError, match=text):
            be.configure(BackendConfig(sc.device, initial_device_pose(sc), {}, options))


def test_example_simulates_a_hand_that_pushes_unless_told_not_to(
        example_installed: Path) -> None:
    """``hand: scenario`` (default): fig8's user (0.4 N along x) pushes the handle, which
    moves along +x and measures exactly that push; ``hand: none``: it stays where it
    started."""
    import numpy as np

    sc = load_scenario('fig8')
    start = initial_device_pose(sc)
    for options, moves in (({}, True), ({'hand': 'none'}, False)):
        be = create_backend(EXAMPLE_NAME)
        be.configure(BackendConfig(sc.device, start, dict(sc.user), options))
        be.activate()
        be.write(np.zeros(start.size))
        for _ in range(100):
            reading = be.read(sc.dt)
        push = np.array(sc.user['wrench'], dtype=float)
        assert bool(reading.pose[0] > start[0]) is moves, (options, reading.pose, start)
        np.testing.assert_array_equal(reading.hand_wrench, push if moves else 0.0 * push)
        be.deactivate()
    with pytest.raises(DeviceError, match="backend_options.hand: expected one of scenario, "
                                          "none, got 'left'"):
        create_backend(EXAMPLE_NAME).configure(BackendConfig(sc.device, start, dict(sc.user),
                                                             {'hand': 'left'}))


SUBJECTS = {
    'sim_maglev': Subject('sim_maglev', Applied),
    'sim_maglev_spatial': Subject('sim_maglev', Applied, scenario='spatial_arm4'),
    # max_force above the scenario's limit: the device gets what the driver's clamp lets through
    EXAMPLE_NAME: Subject(EXAMPLE_NAME, Applied, {'stiffness': 80.0, 'travel': 1.0,
                                                  'max_force': 100.0}),
}
CHECKS: dict[str, Callable[[Bench], None]] = {
    'clamping': check_clamping, 'nonfinite': check_nonfinite, 'watchdog': check_watchdog,
    'lifecycle': check_lifecycle,
}


@pytest.mark.parametrize('check', sorted(CHECKS))
@pytest.mark.parametrize('subject', sorted(SUBJECTS))
def test_backend_conforms(subject: str, check: str, request: pytest.FixtureRequest) -> None:
    if subject == EXAMPLE_NAME:
        request.getfixturevalue('example_installed')
    CHECKS[check](Bench(SUBJECTS[subject]))


def test_example_reports_a_fault_and_the_loop_writes_zero(example_installed: Path) -> None:
    """The example's fault (out of travel) goes through the driver's fault path: zero from
    the next cycle, FAULT in the state, the reason in the diagnostics."""
    from haptic_topology.vocabulary import DeviceStatus

    bench = Bench(Subject(EXAMPLE_NAME, Applied, {'travel': 0.001, 'stiffness': 0.0,
                                                  'damping': 0.0}))
    bench.activate()
    bench.engage()
    faulted = False
    for _ in range(200):
        tick = bench.cycle(bench.limit * 0.5)
        if faulted:
            assert not bench.written[-1].any()
        faulted = bool(tick.status & DeviceStatus.FAULT)
    assert faulted and bench.loop.fault_cycles > 0
    assert 'out of travel' in bench.loop.health()[1]
    bench.release()
