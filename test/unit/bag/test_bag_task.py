"""The task of a bag's run: from the caller's scenario, else the scenario the bag's metadata
names; task_dim 3 alone (planar or spatial_point) is refused, never guessed."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import yaml

from haptic_topology.bag.graph_trace import read_graph_bag
from haptic_topology.errors import BagError
from haptic_topology.vocabulary import TaskSpace

REFERENCE = Path(__file__).resolve().parents[3] / 'bags' / 'reference_fig8'


def _without_scenario(tmp_path: Path) -> Path:
    bag = tmp_path / 'bag'
    shutil.copytree(REFERENCE, bag)
    meta = bag / 'metadata.yaml'
    doc = yaml.safe_load(meta.read_text())
    del doc['rosbag2_bagfile_information']['custom_data']['scenario']
    meta.write_text(yaml.safe_dump(doc))
    return bag


def test_the_task_comes_from_the_bags_scenario() -> None:
    assert read_graph_bag(REFERENCE).trace.task is TaskSpace.PLANAR


def test_task_dim_3_without_a_scenario_is_refused(tmp_path: Path) -> None:
    bag = _without_scenario(tmp_path)
    with pytest.raises(BagError, match=r'bag: task_dim 3 is planar or spatial_point and '
                       r'nothing tells which: metadata.yaml names no scenario that loads '
                       r'\(custom_data.scenario\)$'):
        read_graph_bag(bag)
    assert read_graph_bag(bag, 'fig8').trace.meta['task'] == 'planar'
