"""Loop closures: a closed-chain linkage as its serial chain plus closure constraints.

The paper renders serial linkages and names "linkages with arbitrary topologies, including
multiple closed loops" as future work. A closed chain is described here as a serial chain (the
spanning tree the rest of the package models) plus closures ``phi(q) = 0``, each joining a
point of one link to a point of another link or of the world. The ``loops:`` block of a
linkage file::

    loops:
      - name: ground_pivot      # optional, default loop<i>
        link: rocker            # a link of the chain
        point: [0.07, 0.0, 0.0] # m, in that link's frame
        to: world               # another link, or world (the default)
        to_point: [0.10, 0.0, 0.0]   # m, in the frame of ``to`` (default the origin)
        kind: pin               # pin | spherical | revolute

Kinds and their equations (rows of ``phi`` and of its Jacobian ``J_c``):

* ``pin`` (planar linkages only): the two points coincide in the plane, 2 equations (x, y).
* ``spherical``: the two points coincide, 3 equations (x, y, z). On a planar linkage the z
  row is identically zero: a redundant equation the rank decision drops.
* ``revolute`` (spatial linkages only): the points coincide and the joint axes stay parallel,
  5 equations: ``axis`` (in ``link``'s frame) and ``to_axis`` (in the frame of ``to``,
  default ``axis``) are unit vectors after normalisation.

Units SI: points in m, residual rows in m (points) and rad (axes, to first order).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Any

import numpy as np

from haptic_topology.errors import LinkageError
from haptic_topology.validate import as_str, as_vector, check_keys
from haptic_topology.vocabulary import TaskSpace

#: The name of the world (ground) as the ``to`` of a closure.
WORLD = 'world'


class LoopKind(enum.Enum):
    """The joint that closes a loop."""

    PIN = 'pin'                 # planar revolute: 2 equations
    SPHERICAL = 'spherical'     # ball joint: 3 equations
    REVOLUTE = 'revolute'       # spatial revolute: 5 equations


#: Equations per closure kind.
EQUATIONS = {LoopKind.PIN: 2, LoopKind.SPHERICAL: 3, LoopKind.REVOLUTE: 5}


@dataclass(frozen=True)
class LoopClosure:
    """One closure: ``point`` of ``link`` meets ``to_point`` of ``to`` (a link or
    :data:`WORLD`); for ``revolute`` also ``axis`` (``link`` frame) parallel to ``to_axis``
    (``to`` frame), both unit vectors."""

    name: str
    link: str
    point: np.ndarray
    to: str
    to_point: np.ndarray
    kind: LoopKind
    axis: np.ndarray | None = None
    to_axis: np.ndarray | None = None

    @property
    def equations(self) -> int:
        """Rows of ``phi`` this closure adds (2 pin, 3 spherical, 5 revolute)."""
        return EQUATIONS[self.kind]

    def to_dict(self) -> dict[str, Any]:
        """The YAML entry of this closure (the inverse of :func:`parse_loops`)."""
        out: dict[str, Any] = {'name': self.name, 'link': self.link,
                               'point': self.point.tolist(), 'to': self.to,
                               'to_point': self.to_point.tolist(), 'kind': self.kind.value}
        if self.axis is not None and self.to_axis is not None:
            out['axis'] = self.axis.tolist()
            out['to_axis'] = self.to_axis.tolist()
        return out


def _unit(value: Any, where: str) -> np.ndarray:
    v = as_vector(value, where, 3, error=LinkageError)
    n = float(np.linalg.norm(v))
    if not n > 1e-9:
        raise LinkageError(f'{where}: expected a nonzero axis, got {v.tolist()}')
    return v / n


def parse_loops(raw: Any, where: str, task: TaskSpace,
                link_names: tuple[str, ...]) -> tuple[LoopClosure, ...]:
    """Validate the ``loops:`` list (``where``: its path) against the chain's links."""
    if not isinstance(raw, list) or not raw:
        raise LinkageError(f'{where}: expected a non-empty list of closures, got {raw!r}')
    known = ', '.join(link_names)
    out: list[LoopClosure] = []
    for i, entry in enumerate(raw):
        w = f'{where}[{i}]'
        e = check_keys(entry, w, required=('link', 'point', 'kind'),
                       optional=('name', 'to', 'to_point', 'axis', 'to_axis'),
                       error=LinkageError)
        name = as_str(e.get('name', f'loop{i}'), f'{w}.name', error=LinkageError)
        link = as_str(e['link'], f'{w}.link', error=LinkageError)
        if link not in link_names:
            raise LinkageError(f'{w}.link: unknown link {link!r} (expected one of: {known})')
        to = as_str(e.get('to', WORLD), f'{w}.to', error=LinkageError)
        if to != WORLD and to not in link_names:
            raise LinkageError(f'{w}.to: unknown link {to!r} (expected {WORLD} or one of: '
                               f'{known})')
        if to == link:
            raise LinkageError(f'{w}.to: {to!r} is the closure\'s own link: a loop joins two '
                               'different links (or a link and the world)')
        kind = LoopKind(as_str(e['kind'], f'{w}.kind', tuple(k.value for k in LoopKind),
                               error=LinkageError))
        if kind is LoopKind.PIN and not task.planar:
            raise LinkageError(f'{w}.kind: pin closes a planar loop; a spatial linkage takes '
                               'revolute (5 equations) or spherical (3)')
        if kind is LoopKind.REVOLUTE and task.planar:
            raise LinkageError(f'{w}.kind: revolute closes a spatial loop; a planar linkage '
                               'takes pin (2 equations)')
        point = as_vector(e['point'], f'{w}.point', 3, error=LinkageError)
        to_point = as_vector(e.get('to_point', [0.0, 0.0, 0.0]), f'{w}.to_point', 3,
                             error=LinkageError)
        if task.planar and (point[2] != 0.0 or to_point[2] != 0.0):
            raise LinkageError(f'{w}: point and to_point must have z = 0 on a planar linkage')
        axis = to_axis = None
        if kind is LoopKind.REVOLUTE:
            if 'axis' not in e:
                raise LinkageError(f'{w}.axis: missing required key (the joint axis in the '
                                   f'frame of {link}) for a revolute closure')
            axis = _unit(e['axis'], f'{w}.axis')
            to_axis = _unit(e['to_axis'], f'{w}.to_axis') if 'to_axis' in e else axis.copy()
        elif 'axis' in e or 'to_axis' in e:
            raise LinkageError(f'{w}.axis: only a revolute closure has an axis')
        out.append(LoopClosure(name, link, point, to, to_point, kind, axis, to_axis))
    names = [c.name for c in out]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise LinkageError(f'{where}: duplicate closure names {dup}')
    return tuple(out)
