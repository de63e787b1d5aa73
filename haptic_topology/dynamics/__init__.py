"""Configuration-space dynamics (eq. 1-2), hand Jacobian, its SVD and constraint directions."""

from haptic_topology.dynamics.constraints import (
    ConstraintDirections,
    constraint_directions,
    penalty_weight,
    task_scale,
)
from haptic_topology.dynamics.linkage_dynamics import (
    DynamicsSnapshot,
    LinkageDynamics,
    inverse_operational_inertia,
)
from haptic_topology.dynamics.taskspace import (
    integrate_pose,
    pose_difference,
    pose_from_placement,
    translation_distance,
    wrap_angle,
)

__all__ = ['ConstraintDirections', 'DynamicsSnapshot', 'LinkageDynamics',
           'constraint_directions', 'integrate_pose', 'inverse_operational_inertia',
           'penalty_weight', 'pose_difference', 'pose_from_placement', 'task_scale',
           'translation_distance', 'wrap_angle']
