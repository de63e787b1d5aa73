"""The text of a bag's ``metadata.yaml``: YAML as rosbag2 writes it (libyaml's emitter when
available), and :class:`MetadataText`, which emits the document a
:class:`~haptic_topology.bag.writer.BagWriter` rewrites at every flush once per shape and
then only fills in its numbers."""

from __future__ import annotations

from typing import Any

import yaml

#: libyaml's emitter where PyYAML has it (its wheels do): the same text as the pure-Python
#: ``yaml.safe_dump``, about 5x faster; the recorder rewrites ``metadata.yaml`` at every flush.
_DUMPER = getattr(yaml, 'CSafeDumper', yaml.SafeDumper)


def dump_yaml(data: Any) -> str:
    """``yaml.safe_dump(data, sort_keys=False)``, with libyaml's emitter when available."""
    return yaml.dump(data, Dumper=_DUMPER, sort_keys=False)


def _numbers(node: Any, out: list[int], mark: bool = False) -> Any:
    """The ints of ``node`` (nested dicts and lists) appended to ``out`` in document order;
    with ``mark``, ``node`` with each int replaced by a placeholder (:data:`_MARK` + its
    index)."""
    if isinstance(node, dict):
        return {k: _numbers(v, out, mark) for k, v in node.items()}
    if isinstance(node, list):
        return [_numbers(v, out, mark) for v in node]
    if isinstance(node, int) and not isinstance(node, bool):
        out.append(node)
        return _MARK + len(out) - 1 if mark else node
    return node


#: The placeholders of :class:`MetadataText`: 19-digit ints that no other text of the
#: document holds (checked: a template whose placeholders are not each found once is none).
_MARK = 4_000_000_000_000_000_000


class MetadataText:
    """``dump_yaml`` of a bag's ``metadata.yaml`` document for each flush, emitted once per
    shape (the storage files it lists and its ``custom_data``, which the recorder completes
    with the device's identity once the driver reports it) with a placeholder for each
    number, which each flush fills in: the numbers (counts, times) are all that changes, and
    emitting the YAML again cost ~2 ms a flush for the graph's 17 topics (their QoS text is
    most of its 11 kB)."""

    def __init__(self) -> None:
        self._shape: tuple[str, ...] | None = None
        self._pieces: list[str] | None = None

    def __call__(self, info: dict[str, Any]) -> str:
        doc = {'rosbag2_bagfile_information': info}
        values: list[int] = []
        custom = info.get('custom_data') or {}
        shape = (*(f['path'] for f in info['files']), *(f'{k}={v}' for k, v in custom.items()))
        if shape != self._shape:
            self._shape = shape
            text = dump_yaml(_numbers(doc, values, mark=True))
            pieces: list[str] = []
            rest = text
            for i in range(len(values)):
                mark = str(_MARK + i)
                head, found, rest = rest.partition(mark)
                if not found or text.count(mark) != 1:
                    break
                pieces.append(head)
            self._pieces = [*pieces, rest] if len(pieces) == len(values) else None
            values.clear()
        if self._pieces is None:
            return dump_yaml(doc)
        _numbers(doc, values)
        out = [self._pieces[0]]
        for v, piece in zip(values, self._pieces[1:], strict=True):
            out += (str(v), piece)
        return ''.join(out)
