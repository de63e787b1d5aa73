"""``haptic-topology devices``: the device backends this installation has, whether each vendor
backend's package and library load (:func:`~haptic_topology.device.vendor.probe`), and the
devices connected to them.

Example (the Force Dimension emulator, ``FDSDK=.venv/fdsdk-emulator``)::

    backend         kind         library / how it connects                devices
    sim_maglev      built in     simulated maglev of the paper's lab      -
    ros_topics      built in     a ROS 2 driver's topics                  -
    network         built in     a device controller over UDP             -
    forcedimension  vendor       found: .../libdrd.so.3.16.0 (SDK 3.16.0-0)  omega.3 serial 11029
"""

from __future__ import annotations

import argparse
import importlib.metadata as md

from haptic_topology.device.backend import BUILTIN_BACKENDS, ENTRY_POINT_GROUP
from haptic_topology.device.vendor import VENDOR_BACKENDS, probe

#: What each built-in backend that is not a vendor's connects to.
_BUILT_IN = {
    'sim_maglev': 'simulated maglev of the paper\'s lab',
    'ros_topics': 'a ROS 2 driver\'s topics (pose, twist, wrench)',
    'network': 'a device controller over UDP',
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('--backend', action='append', metavar='NAME',
                        help='only these backends (repeatable); default: all')


def rows(names: list[str] | None = None) -> list[tuple[str, str, str, str]]:
    """``(backend, kind, library, devices)`` per backend (all, or ``names``)."""
    entry_points = sorted(ep.name for ep in md.entry_points(group=ENTRY_POINT_GROUP))
    every = list(BUILTIN_BACKENDS) + [n for n in entry_points if n not in BUILTIN_BACKENDS]
    out = []
    for name in every if not names else [n for n in every if n in names]:
        if name in VENDOR_BACKENDS:
            p = probe(name)
            s = p.support
            if p.found:
                library = f'found: {p.detail}'
                devices = ', '.join(p.devices) or 'none connected'
            else:
                library = (f'missing: {s.package} / {s.library} (set {s.variable}): '
                           f'{p.detail}')
                devices = '-'
            out.append((name, 'vendor', library, devices))
        elif name in _BUILT_IN:
            out.append((name, 'built in', _BUILT_IN[name], '-'))
        else:
            out.append((name, 'entry point', 'a backend of an installed distribution', '-'))
    return out


def run(args: argparse.Namespace) -> int:
    """Print the table (module doc); 0 whatever is found."""
    table = [('backend', 'kind', 'library / how it connects', 'devices')]
    table += rows(args.backend)
    widths = [max(len(r[i]) for r in table) for i in range(3)]
    for r in table:
        print('  '.join(c.ljust(w) for c, w in zip(r[:3], widths, strict=True)) + '  ' + r[3])
    return 0
