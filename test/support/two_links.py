"""A two-link spatial URDF for contact tests: link 1 yaws about z at the origin, link 2 turns
about (0, 1, 1) at x = 0.1 of link 1; each link's ``<collision>`` elements given by the test."""

from __future__ import annotations

from pathlib import Path

from haptic_topology.model import Linkage, load_linkage

INERTIAL = ('<inertial><mass value="1"/><inertia ixx="0.01" iyy="0.01" izz="0.01" ixy="0" '
            'ixz="0" iyz="0"/></inertial>')


def two_link_urdf(tmp_path: Path, l1: str, l2: str = '', name: str = 'm.urdf') -> Linkage:
    """The linkage of the URDF written to ``tmp_path / name``, link 1 carrying the collision
    elements ``l1``, link 2 ``l2`` (1 kg links, joints within +-3 rad)."""
    path = tmp_path / name
    limit = '<limit lower="-3" upper="3" effort="1" velocity="1"/>'
    path.write_text(f'''<robot name="m">
  <link name="base"/>
  <link name="l1">{INERTIAL}{l1}</link>
  <link name="l2">{INERTIAL}{l2}</link>
  <joint name="j1" type="revolute"><parent link="base"/><child link="l1"/>
    <axis xyz="0 0 1"/>{limit}</joint>
  <joint name="j2" type="revolute"><parent link="l1"/><child link="l2"/>
    <origin xyz="0.1 0 0"/><axis xyz="0 1 1"/>{limit}</joint>
</robot>''')
    return load_linkage(path)
