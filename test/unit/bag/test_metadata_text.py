"""``metadata.yaml`` at each flush: the text ``MetadataText`` fills in is the YAML emitted for
the whole document, whatever its numbers, files and strings."""

from __future__ import annotations

import numpy as np

from haptic_topology.bag.metadata_text import _MARK, MetadataText, dump_yaml
from haptic_topology.bag.writer import FileInfo, TopicSpec, make_qos, metadata_info
from haptic_topology.nodes.qos import TOPIC_QOS
from haptic_topology.nodes.recorder import RECORDED, _bag_qos

TOPICS = [TopicSpec('/' + t, RECORDED[t][1], (_bag_qos(TOPIC_QOS[t]),)) for t in RECORDED]
HASHES = {t.msgtype: 'RIHS01_' + f'{n:064x}' for n, t in enumerate(TOPICS)}


def _info(rng: np.random.Generator, files: int, custom: dict[str, str]) -> dict:
    names = [f'b_{k}.mcap' for k in range(files)]
    start = int(rng.integers(0, 2**62))
    spans = [FileInfo(n, start + k * 10**9, start + k * 10**9 + int(rng.integers(0, 10**9)),
                      int(rng.integers(0, 10**6))) for k, n in enumerate(names)]
    counts = rng.integers(0, 10**7, size=len(TOPICS)).tolist()
    counts[0] = 0                     # a topic nothing came on
    end = start + int(rng.integers(0, 10**12))
    return metadata_info(spans, TOPICS, HASHES, counts, start, end, custom)


def test_filled_in_text_is_the_emitted_document() -> None:
    rng = np.random.default_rng(7)
    text = MetadataText()
    custom = {'recorded_by': 'haptic_topology recorder', 'scenario': 'circle', 'graph_id': '42'}
    for files in (1, 1, 1, 2, 2, 3, 1):         # a new shape now and then (a split)
        for _ in range(5):
            info = _info(rng, files, custom)
            assert text(info) == dump_yaml({'rosbag2_bagfile_information': info})


def test_custom_data_completed_during_the_recording_is_written() -> None:
    """The recorder adds the device's identity to ``custom_data`` once the driver reports
    it: the next flush's text has it (the template is not the one of the first flushes)."""
    rng = np.random.default_rng(9)
    text = MetadataText()
    custom = {'recorded_by': 'haptic_topology recorder', 'scenario': 'fig8_point'}
    for extra in ({}, {}, {'device': 'forcedimension omega.3 serial 11029'}, {},
                  {'device': 'forcedimension omega.3 serial 11029', 'device_serial': '11029'}):
        custom = {**custom, **extra}
        info = _info(rng, 1, custom)
        assert text(info) == dump_yaml({'rosbag2_bagfile_information': info})


def test_a_string_that_holds_a_placeholder_falls_back_to_emitting() -> None:
    rng = np.random.default_rng(8)
    text = MetadataText()
    custom = {'graph_id': str(_MARK + 3)}       # the digits of a placeholder in a string
    for _ in range(3):
        info = _info(rng, 2, custom)
        assert text(info) == dump_yaml({'rosbag2_bagfile_information': info})
    assert text._pieces is None


def test_an_empty_bag_and_a_qos_of_its_own() -> None:
    topics = [TopicSpec('/x', TOPICS[0].msgtype, (make_qos(True, 7),))]
    info = metadata_info([FileInfo('b_0.mcap', 0, 0, 0)], topics, HASHES, [0], 0, 0, None)
    assert MetadataText()(info) == dump_yaml({'rosbag2_bagfile_information': info})
