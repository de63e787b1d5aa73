"""The device's identity (``hardware_id`` and the vendor's ``device_*`` diagnostics values of
``device_driver: loop``, :class:`~haptic_topology.device.vendor.DeviceIdentity`) goes from the
bag's ``/diagnostics`` into the analysis (``Run.device``), which ``run`` writes into
``summary.json``."""

from __future__ import annotations

from pathlib import Path

from haptic_topology.bag.analyze import reduce_bag
from haptic_topology.bag.reader import iter_messages, open_bag
from haptic_topology.bag.writer import BagWriter, TopicSpec, make_qos
from haptic_topology.device.vendor import DeviceIdentity
from haptic_topology.messages.definitions import message_definitions, typestore_with_haptic_msgs

REFERENCE = Path(__file__).resolve().parents[3] / 'bags' / 'reference_fig8'
DIAG = 'diagnostic_msgs/msg/DiagnosticArray'


def test_the_newest_device_status_names_the_device(tmp_path: Path) -> None:
    ts = typestore_with_haptic_msgs()
    bag = open_bag(REFERENCE)
    topics = bag.metadata_topics()
    names = sorted(topics)
    out = tmp_path / 'bag'
    w = BagWriter(out, [TopicSpec(t, topics[t], (make_qos(False, 1),)) for t in names], ts,
                  sources=message_definitions(),
                  custom=(bag.metadata or {}).get('custom_data') or {})
    index = {t: i for i, t in enumerate(names)}
    last = 0
    header = None
    for m in iter_messages(bag):
        w.write(index[m.topic], m.log_time, bytes(m.data))
        last = max(last, m.log_time)
        if header is None and m.topic == '/diagnostics':
            header = ts.deserialize_cdr(bytes(m.data), DIAG).header
    ident = DeviceIdentity('Force Dimension', 'omega.3', '11029', '3.16.0', 'sphere r 0.075 m')
    kv = ts.types['diagnostic_msgs/msg/KeyValue']
    status = ts.types['diagnostic_msgs/msg/DiagnosticStatus'](
        0, 'device_driver: loop', 'ok', ident.hardware_id('forcedimension'),
        [kv(k, v) for k, v in ident.values().items()])
    w.write(index['/diagnostics'], last + 1,
            bytes(ts.serialize_cdr(ts.types[DIAG](header, [status]), DIAG)))
    w.close()
    run = reduce_bag(out, 'fig8', plot=False)
    assert run.device == {'hardware_id': 'forcedimension omega.3 serial 11029',
                          **ident.values()}
    assert reduce_bag(REFERENCE, 'fig8', plot=False).device == {
        'hardware_id': 'sim_maglev planar'}
