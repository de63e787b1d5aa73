"""The link-level types of a linkage description: joint kinds, links and their URDF collision
shapes (SI units, link frame at the joint). The linkage itself and its YAML form:
:mod:`haptic_topology.model.linkage`; the URDF import: :mod:`haptic_topology.model.urdf_import`."""

from __future__ import annotations

import enum
from dataclasses import dataclass, field

import numpy as np


class JointType(enum.Enum):
    """One-DOF joint kinds of a serial linkage."""

    REVOLUTE = 'revolute'
    PRISMATIC = 'prismatic'


@dataclass(frozen=True)
class CollisionShape:
    """One ``<collision>`` element of a URDF link, placed in the frame of the chain link that
    carries it (after fixed joints are merged and side branches locked).

    ``kind``: ``sphere`` (``size = (radius,)``), ``capsule`` (``(radius, length)``, axis along
    the placement's z, as ``<capsule radius length>`` in Drake/Gazebo URDFs), ``cylinder``
    (``(radius, length)``), ``box`` (``(x, y, z)`` full sizes) or ``mesh`` (its ``scale``
    ``(sx, sy, sz)``, and ``mesh``: the ``filename`` as the URDF writes it, resolved by the
    contacts: :mod:`haptic_topology.model.meshes`); ``xyz`` (m) and ``rotation`` (3 x 3,
    row-major) place its centre (a mesh: its frame) in the link frame; ``urdf_link`` names the
    URDF link it was declared on. SI units."""

    kind: str
    size: tuple[float, ...]
    xyz: tuple[float, ...]
    rotation: tuple[float, ...]
    urdf_link: str
    mesh: str = ''


@dataclass(frozen=True)
class LinkSpec:
    """One link and the joint that moves it (SI units, link frame at the joint)."""

    name: str
    joint: JointType
    length: float
    mass: float
    com: np.ndarray                     # (3,) m, link frame
    inertia: np.ndarray                 # (3, 3) kg m^2 about the COM, link frame
    axis: np.ndarray                    # (3,) unit joint axis, link frame
    origin_xyz: np.ndarray | None = None  # (3,) m in the previous link frame; None = default
    origin_rpy: np.ndarray = field(default_factory=lambda: np.zeros(3))
    joint_name: str = ''                # '' = joint_<name>; URDF joints keep their own names
    #: The URDF's collision geometry on this link (None: not a URDF link, the contacts'
    #: default capsule applies; ``()``: a URDF link without ``<collision>``).
    collision: tuple[CollisionShape, ...] | None = None

    @property
    def joint_label(self) -> str:
        """Name of the joint that moves this link (Pinocchio model, error messages)."""
        return self.joint_name or f'joint_{self.name}'


