"""``PublisherWatch`` over a stand-in for the node's graph cache (what
``get_publishers_info_by_topic`` returns), so each check is exact; the real graph is in
``test/graph/test_foreign_graph.py``."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

from haptic_topology.nodes.diagnostics import UNKNOWN_NODE, PublisherWatch


class _Graph:
    """The few Node methods the watch uses; ``publishers``: topic -> [(namespace, name)]."""

    def __init__(self) -> None:
        self.publishers: dict[str, list[tuple[str, str]]] = {}
        self.errors: list[str] = []

    def resolve_topic_name(self, topic: str) -> str:
        return '/' + topic

    def get_namespace(self) -> str:
        return '/'

    def create_timer(self, *_: Any, **__: Any) -> None:
        return None

    def get_logger(self) -> Any:
        return SimpleNamespace(error=self.errors.append)

    def get_publishers_info_by_topic(self, topic: str) -> list[Any]:
        return [SimpleNamespace(node_namespace=ns, node_name=name,
                                endpoint_gid=list(f'{ns}{name}#{k}'.encode()))
                for k, (ns, name) in enumerate(self.publishers.get(topic, []))]


def test_foreign_publishers_are_named_reported_at_once_and_logged_once() -> None:
    graph = _Graph()
    reports: list[int] = []
    watch = PublisherWatch(graph, {'haptic/lmi/update': ('ve_sim',)},   # type: ignore[arg-type]
                           lambda: reports.append(1))
    graph.publishers['/haptic/lmi/update'] = [('/', 've_sim'), ('/', UNKNOWN_NODE)]
    watch.check()
    assert watch.problem() is None and reports == [] and graph.errors == []
    # another name, and the expected name in another namespace
    graph.publishers['/haptic/lmi/update'] += [('/', 'intruder'), ('/lab2', 've_sim')]
    watch.check()
    assert watch.values() == {'foreign_publishers': 'haptic/lmi/update: /intruder, /lab2/ve_sim'}
    assert watch.problem() == 'foreign publisher(s): haptic/lmi/update: /intruder, /lab2/ve_sim'
    assert reports == [1] and len(graph.errors) == 1
    values: dict[str, str] = {}
    assert watch.merge(values, 0, 'ok') == (
        2, 'foreign publisher(s): haptic/lmi/update: /intruder, /lab2/ve_sim; ok')
    watch.check()                                   # still there: nothing new
    assert reports == [1] and len(graph.errors) == 1
    graph.publishers['/haptic/lmi/update'] = [('/', 've_sim')]
    watch.check()                                   # gone
    assert watch.problem() is None and watch.merge({}, 0, 'ok') == (0, 'ok')
    graph.publishers['/haptic/lmi/update'].append(('/', 'intruder'))
    watch.check()                                   # back: reported at once, logged once
    assert reports == [1, 1] and len(graph.errors) == 1


def test_gates_see_own_endpoints_and_name_a_topic_whose_own_publisher_is_gone() -> None:
    graph = _Graph()
    watch = PublisherWatch(graph, {'haptic/lmi/update': ('ve_sim',)})   # type: ignore[arg-type]
    gate = watch.gates['haptic/lmi/update']
    graph.publishers['/haptic/lmi/update'] = [('/', 've_sim')]
    watch.check()
    assert gate.own == frozenset({b'/ve_sim#0'}) and gate.foreign == () and gate.distinct()
    graph.publishers['/haptic/lmi/update'] = [('/', 'intruder')]        # own one gone
    watch.check()
    assert gate.own == frozenset() and gate.foreign == ('/intruder',) and not gate.distinct()
    said = [e for e in graph.errors if 'cannot be told' in e]
    assert said == ["haptic/lmi/update: no ve_sim of this graph publishes it and /intruder "
                    "does: this graph's messages on it cannot be told from foreign ones; none "
                    'is applied until ve_sim is back']
    watch.check()                                 # still so: said once
    assert len([e for e in graph.errors if 'cannot be told' in e]) == 1
    assert watch.problem() == (
        "haptic/lmi/update: no ve_sim of this graph publishes it and /intruder does: this "
        "graph's messages on it cannot be told from foreign ones; foreign publisher(s): "
        'haptic/lmi/update: /intruder')
    graph.publishers['/haptic/lmi/update'] = [('/', 'intruder'), ('/', 've_sim')]
    watch.check()                                 # back: both, told apart by graph_id
    assert gate.distinct() and watch.problem() == (
        'foreign publisher(s): haptic/lmi/update: /intruder')
