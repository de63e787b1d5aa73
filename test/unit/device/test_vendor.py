"""The shared vendor layer (``haptic_topology.device.vendor``): the point mapping, grasp and
clutch, identity, the missing-library error and the registry. Exact values throughout: the
objects are pure and deterministic."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from haptic_topology.device.vendor import (
    VENDOR_BACKENDS,
    DeviceIdentity,
    VendorHand,
    parse_vendor_options,
    probe,
    vendor_support,
)
from haptic_topology.errors import ConfigError, DeviceError, VendorLibraryMissing
from haptic_topology.vocabulary import DeviceStatus, TaskSpace

SP = TaskSpace.SPATIAL_POINT
DT = 1e-3


def hand(options: dict, task: TaskSpace = SP, start: tuple = (0.1, 0.0, 0.0)) -> VendorHand:
    opts, rest = parse_vendor_options(options, 'vend', task, {})
    assert rest == {}
    return VendorHand(opts, np.array(start[:task.dim]))


def test_module_doc_example_grasp_clutch_and_indexing() -> None:
    """The module doc's example: the first grasp aligns, the clutch holds the task position
    while the handle moves, releasing it goes on from there."""
    h = hand({'scale': 0.001, 'clutch_button': 1})
    r = h.reading((10.0, 0.0, 0.0), (0.0, 0.0, 0.0), 0, DT)
    np.testing.assert_allclose(r.pose, [0.1, 0.0, 0.0], rtol=0, atol=1e-15)
    r = h.reading((20.0, 0.0, 0.0), (5.0, 0.0, 0.0), 0, DT)
    np.testing.assert_allclose(r.pose, [0.11, 0.0, 0.0], rtol=0, atol=1e-15)
    np.testing.assert_allclose(r.twist, [0.005, 0.0, 0.0], rtol=0, atol=1e-15)
    r = h.reading((0.0, 0.0, 0.0), (-5.0, 0.0, 0.0), 0b10, DT)       # clutched
    np.testing.assert_allclose(r.pose, [0.11, 0.0, 0.0], rtol=0, atol=1e-15)
    np.testing.assert_array_equal(r.twist, 0.0)
    assert r.status == DeviceStatus.WATCHDOG and not h.grasping
    assert h.force(np.array([1.0, 2.0, 3.0])) == (0.0, 0.0, 0.0)
    h.reading((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 0, DT)               # released
    r = h.reading((5.0, 0.0, 0.0), (0.0, 0.0, 0.0), 0, DT)
    np.testing.assert_allclose(r.pose, [0.115, 0.0, 0.0], rtol=0, atol=1e-15)
    assert h.grasps == 2 and h.clutched_cycles == 1


def test_engage_button_grasps_and_the_force_fades_in() -> None:
    """Without the engage button held: zero force, the task pose stays at the start, WATCHDOG;
    held: the force rises by dt / ramp per cycle (10 ms ramp: 10 cycles) to the command;
    released: zero at once."""
    h = hand({'engage_button': 0, 'grasp_ramp_ms': 10.0})
    u = np.array([1.0, -2.0, 0.5])
    for p in ((0.0, 0.0, 0.0), (0.02, 0.0, 0.0)):
        r = h.reading(p, (1.0, 0.0, 0.0), 0, DT)
        np.testing.assert_array_equal(r.pose, [0.1, 0.0, 0.0])
        assert r.status == DeviceStatus.WATCHDOG
        assert h.force(u) == (0.0, 0.0, 0.0)
    scales = []
    for _ in range(12):
        r = h.reading((0.02, 0.0, 0.0), (0.0, 0.0, 0.0), 0b1, DT)
        scales.append(h.scale)
        f = h.force(u)
        np.testing.assert_allclose(f, h.scale * u, rtol=1e-15, atol=0)
    np.testing.assert_allclose(scales[:10], np.arange(1, 11) / 10, rtol=1e-12)
    assert scales[10:] == [1.0, 1.0] and r.status == DeviceStatus.OK
    np.testing.assert_array_equal(h.force(u), u)
    np.testing.assert_array_equal(r.pose, [0.1, 0.0, 0.0])      # grasped where it stayed
    h.reading((0.02, 0.0, 0.0), (0.0, 0.0, 0.0), 0, DT)
    assert h.force(u) == (0.0, 0.0, 0.0)


@pytest.mark.parametrize(('options', 'buttons', 'hint'), [
    ({'engage_button': 0}, (0b1, 0b1, 0b0, 0b0, 0b1),
     'release and press the engage button (button 0) to grasp again'),
    ({'clutch_button': 1}, (0b0, 0b0, 0b10, 0b10, 0b0),
     'press and release the clutch button (button 1) to grasp again')])
def test_a_released_hand_grasps_again_only_after_letting_go(
        options: dict, buttons: tuple[int, ...], hint: str) -> None:
    """``release()`` (a device back after a loss): whatever the buttons said before, the hand
    grasps again only once they have asked to let go and then to grasp; the position goes on
    from where it stayed and the force fades in again."""
    h = hand({'scale': 0.001, 'grasp_ramp_ms': 2.0, **options})
    u = np.array([1.0, 0.0, 0.0])
    grasp = buttons[0]
    h.reading((10.0, 0.0, 0.0), (0.0, 0.0, 0.0), grasp, DT)
    h.reading((10.0, 0.0, 0.0), (0.0, 0.0, 0.0), grasp, DT)
    assert h.grasping and h.force(u) == (1.0, 0.0, 0.0)
    h.release()
    assert not h.grasping and h.force(u) == (0.0, 0.0, 0.0)
    assert h.regrasp_hint() == hint
    got = []
    for k, b in enumerate(buttons[1:]):        # the handle moved 30 mm meanwhile
        r = h.reading((40.0 + k, 0.0, 0.0), (0.0, 0.0, 0.0), b, DT)
        got.append((h.grasping, h.force(u)[0], r.status))
    W = DeviceStatus.WATCHDOG
    assert got == [(False, 0.0, W), (False, 0.0, W), (False, 0.0, W), (True, 0.5, W)]
    np.testing.assert_allclose(r.pose, [0.1, 0.0, 0.0], rtol=0, atol=1e-15)
    r = h.reading((41.0 + k, 0.0, 0.0), (0.0, 0.0, 0.0), buttons[-1], DT)
    assert r.status == DeviceStatus.OK and h.force(u) == (1.0, 0.0, 0.0) and h.grasps == 2
    np.testing.assert_allclose(r.pose, [0.101, 0.0, 0.0], rtol=0, atol=1e-15)


def test_a_released_hand_without_buttons_stays_released() -> None:
    h = hand({})
    h.reading((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 0, DT)
    h.release()
    for _ in range(5):
        h.reading((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 0, DT)
    assert not h.grasping and h.force(np.ones(3)) == (0.0, 0.0, 0.0)
    assert h.regrasp_hint() == ('no engage or clutch button is configured: forces resume at '
                                'the next activation of device_driver')


def test_axes_scale_and_force_scale_map_both_ways() -> None:
    """``axes: [y, -x, z]`` (task x is device y), mm, force in units of 0.5 N: the handle at
    device (10, 20, 0) mm moves by task (0.020, -0.010, 0); a task force (1, 0, 0) N is device
    (0, 2, 0); an explicit origin maps absolutely from the first grasp."""
    h = hand({'axes': ['y', '-x', 'z'], 'scale': 0.001, 'force_scale': 0.5,
              'origin': [0.1, 0.0, 0.0], 'grasp_ramp_ms': 0})
    r = h.reading((10.0, 20.0, 0.0), (1.0, 0.0, 0.0), 0, DT)
    np.testing.assert_allclose(r.pose, [0.12, -0.01, 0.0], rtol=0, atol=1e-15)
    np.testing.assert_allclose(r.twist, [0.0, -0.001, 0.0], rtol=0, atol=1e-15)
    np.testing.assert_allclose(h.force(np.array([1.0, 0.0, 0.0])), [0.0, 2.0, 0.0], atol=1e-15)


def test_planar_point_keeps_x_y_and_never_pushes_along_z() -> None:
    h = hand({'grasp_ramp_ms': 0}, TaskSpace.PLANAR_POINT, (0.0, 0.0))
    h.reading((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 0, DT)
    r = h.reading((0.01, 0.02, 0.03), (0.1, 0.2, 0.3), 0, DT)
    np.testing.assert_allclose(r.pose, [0.01, 0.02], rtol=1e-15)
    np.testing.assert_allclose(r.twist, [0.1, 0.2], rtol=1e-15)
    assert r.hand_wrench.shape == (2,) and not r.hand_wrench.any()
    assert h.force(np.array([1.0, -1.0])) == (1.0, -1.0, 0.0)
    assert h.force(np.array([np.nan, 1.0])) == (0.0, 1.0, 0.0)


@pytest.mark.parametrize(('options', 'task', 'text'), [
    ({'port': 3}, SP, r"vend: backend_options: unknown option 'port' \(expected some of: axes, "
                      "clutch_button, engage_button, force_scale, grasp_ramp_ms, origin, "
                      r"scale, speed\)"),
    ({'engage_button': 40}, SP, 'vend: backend_options.engage_button: expected a button '
                                'index 0-31 or null'),
    ({'engage_button': 1, 'clutch_button': 1}, SP, 'backend_options.clutch_button: expected '
                                                   'another button than engage_button'),
    ({'scale': 0}, SP, r'backend_options.scale: expected a number in \(0, inf\], got 0'),
    ({'origin': [0, 0]}, SP, 'backend_options.origin: expected 3 numbers'),
    ({'axes': ['x', 'x', 'z']}, SP, 'vend: backend_options.axes: expected 3 signed'),
    ({}, TaskSpace.PLANAR, 'vend: a planar task needs torque; a 3-axis device renders a '
                           'point grasp only'),
])
def test_bad_options_name_the_field(options: dict, task: TaskSpace, text: str) -> None:
    with pytest.raises(DeviceError, match=text):
        parse_vendor_options(options, 'vend', task, {'speed': 1.0})


def test_own_options_come_back_with_their_defaults() -> None:
    _, rest = parse_vendor_options({'speed': 2.0, 'scale': 2.0}, 'vend', SP,
                                   {'speed': 1.0, 'serial': None})
    assert rest == {'speed': 2.0, 'serial': None}


def test_identity_names_the_unit() -> None:
    ident = DeviceIdentity('Force Dimension', 'omega.3', '12345', '3.16.0',
                           'sphere r 0.075 m')
    assert ident.hardware_id('forcedimension') == 'forcedimension omega.3 serial 12345'
    assert DeviceIdentity('X', 'falcon').hardware_id('fd') == 'fd falcon'
    assert ident.values() == {'device_vendor': 'Force Dimension', 'device_model': 'omega.3',
                              'device_serial': '12345', 'device_sdk': '3.16.0',
                              'device_workspace': 'sphere r 0.075 m'}


def test_missing_library_is_one_line_that_survives_pickling() -> None:
    exc = VendorLibraryMissing('forcedimension', 'forcedimension-core', 'libdrd', 'FDSDK',
                               'Could not find libdrd.')
    text = ('forcedimension: cannot load libdrd through the Python package forcedimension-core '
            '(Could not find libdrd.); install both and set FDSDK (docs/devices.md)')
    assert str(exc) == text and '\n' not in text
    assert isinstance(exc, ConfigError) and isinstance(exc, DeviceError)
    back = pickle.loads(pickle.dumps(exc))
    assert str(back) == text and back.detail == 'Could not find libdrd.'


def test_registry_knows_vendor_backends_only() -> None:
    assert all(':' in spec for spec in VENDOR_BACKENDS.values())
    assert vendor_support('sim_maglev') is None
    with pytest.raises(DeviceError, match='sim_maglev: not a vendor backend'):
        probe('sim_maglev')
