"""A two-link URDF for contact tests: link 1 yaws about z at the origin, link 2 turns about
``axis2`` at x = 0.1 of link 1; each link's ``<collision>`` elements given by the test."""

from __future__ import annotations

from pathlib import Path

from haptic_topology.model import Linkage, load_linkage


def two_link_urdf(tmp_path: Path, l1: str, l2: str = '', name: str = 'm.urdf',
                  axis2: str = '0 1 1', planar: bool = False, inertia: float = 0.01,
                  robot: str = 'm') -> Linkage:
    """The linkage of the URDF ``robot`` written to ``tmp_path / name``, link 1 carrying the
    collision elements ``l1``, link 2 ``l2`` (1 kg links of principal moments ``inertia``,
    kg m^2; joints within +-3 rad); ``planar``: a planar task."""
    path = tmp_path / name
    limit = '<limit lower="-3" upper="3" effort="1" velocity="1"/>'
    inertial = (f'<inertial><mass value="1"/><inertia ixx="{inertia:g}" iyy="{inertia:g}" '
                f'izz="{inertia:g}" ixy="0" ixz="0" iyz="0"/></inertial>')
    task = '<haptic_topology task="planar"/>' if planar else ''
    path.write_text(f'''<robot name="{robot}">
  {task}
  <link name="base"/>
  <link name="l1">{inertial}{l1}</link>
  <link name="l2">{inertial}{l2}</link>
  <joint name="j1" type="revolute"><parent link="base"/><child link="l1"/>
    <axis xyz="0 0 1"/>{limit}</joint>
  <joint name="j2" type="revolute"><parent link="l1"/><child link="l2"/>
    <origin xyz="0.1 0 0"/><axis xyz="{axis2}"/>{limit}</joint>
</robot>''')
    return load_linkage(path)
