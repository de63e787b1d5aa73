"""Graph identity of messages (``messages.check.graph_wire``, ``GraphFilter``)."""

from __future__ import annotations

from types import SimpleNamespace

from haptic_topology.messages.check import GraphFilter, graph_wire


def test_graph_wire_is_zero_for_the_default_graph_and_a_stable_63_bit_value_else() -> None:
    assert graph_wire('') == 0
    a, b = graph_wire('fig8-0123456789abcdef'), graph_wire('fig8-0123456789abcdee')
    assert a == graph_wire('fig8-0123456789abcdef')          # every node computes the same
    assert a != b
    assert 0 < a < 2 ** 63 and 0 < b < 2 ** 63               # fits int64 tools, never 0
    # the value the nodes put on the wire, fixed: bags of one release read in the next
    assert graph_wire('another-lab') == 2767034319018177373


def test_graph_filter_passes_its_own_graph_and_counts_the_others_per_topic() -> None:
    own = GraphFilter('lab-a')
    mine = SimpleNamespace(graph_id=graph_wire('lab-a'))
    other = SimpleNamespace(graph_id=graph_wire('lab-b'))
    default = SimpleNamespace(graph_id=0)
    recorded_before_the_field = SimpleNamespace()
    assert own.own(mine, 'haptic/lmi/update')
    assert not own.own(other, 'haptic/lmi/update')
    assert not own.own(default, 'haptic/lmi/update')
    assert not own.own(recorded_before_the_field, 'haptic/hand_inputs')
    assert own.total == 3
    assert own.values() == {'graph_id': 'lab-a', 'foreign_messages': '3',
                            'foreign haptic/hand_inputs': '1',
                            'foreign haptic/lmi/update': '2'}
    default_graph = GraphFilter('')
    assert default_graph.own(default, 't') and default_graph.own(recorded_before_the_field, 't')
    assert not default_graph.own(mine, 't')
    assert default_graph.values() == {'graph_id': '', 'foreign_messages': '1',
                                      'foreign t': '1'}
