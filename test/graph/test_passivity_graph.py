"""The passivity controller in the wall-clock graph: fig6 with a penalty 1,000 times stiffer
and no damping (``k_tc`` 1e4 N/(m kg), ``b_tc`` 0: beyond the Colgate-Schenkel bound of a 1 kg
device at 1 kHz, unstable in ``simulate``), run with ``run_graph`` on the real-time graph
(hosted layout) with the controller enabled and disabled.

What holds on any machine is asserted, nothing about timing: the controller's last
``/diagnostics`` status in the bag says it was on and acted (cycles > 0) in the run with it,
off and never acting in the run without; the observer of the run without it went below zero
(the penalty without damping generates energy whatever the periods). The figures of both runs
(observer minimum and end, drift) are printed by ``bench/passivity_wall_clock.py``.

Every graph runs in a domain of its own (``spare_domains``); every wait has a deadline.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from haptic_topology.bag.reader import decoder, iter_messages, open_bag
from haptic_topology.bringup.options import param_overrides
from haptic_topology.bringup.run import run_graph
from haptic_topology.bringup.watch import CONTROLLER_STATUS
from haptic_topology.paths import config_dir

pytestmark = pytest.mark.graph

PARAMS = config_dir() / 'haptic_topology.yaml'
DURATION = 1.0          # s of wall clock from engagement


def _last_controller_status(bag: Path) -> dict[str, str]:
    """The key/values of the controller's last ``/diagnostics`` status in ``bag``."""
    decode = decoder()
    last: dict[str, str] = {}
    for raw in iter_messages(open_bag(bag), ['/diagnostics']):
        for status in decode(raw).status:
            if status.name == CONTROLLER_STATUS:
                last = {kv.key: kv.value for kv in status.values}
    return last


def _run(tmp_path: Path, passivity: str, domain: int) -> dict[str, str]:
    bag = tmp_path / f'fig6_stiff_{passivity}'
    codes = run_graph('fig6', 'penalty', DURATION, bag, PARAMS, 'hosted',
                      startup_timeout=90.0, domain_id=domain,
                      overrides=param_overrides(['lmi_controller:k_tc:=10000.0',
                                                 'lmi_controller:b_tc:=0.0',
                                                 f'lmi_controller:passivity:={passivity}']))
    assert all(c == 0 for c in codes.values()), codes
    return _last_controller_status(bag)


def test_wall_clock_graph_runs_the_passivity_controller_on_an_unstable_penalty(
        tmp_path: Path, spare_domains: list[int]) -> None:
    on = _run(tmp_path, 'enabled', spare_domains[0])
    off = _run(tmp_path, 'disabled', spare_domains[1])
    assert on['passivity_controller'] == 'on' and int(on['passivity_cycles']) > 0, on
    assert off['passivity_controller'] == 'off' and int(off['passivity_cycles']) == 0, off
    assert float(off['passivity_observer_min_j']) < 0.0, off
