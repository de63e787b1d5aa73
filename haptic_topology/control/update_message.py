"""An ``LmiUpdate`` message (as rclpy or a bag's reader decodes it: any object with its fields)
to the :class:`~haptic_topology.control.lmi.LmiSnapshot` it carries, every field checked: what
``lmi_controller`` takes (``haptic_topology.nodes.convert`` re-exports it) and what a
bag's offline replay of the controller takes (``haptic_topology.bag.energy_series``), one
function so both see the same numbers."""

from __future__ import annotations

from typing import Any

import numpy as np

from haptic_topology.control.lmi import LmiSnapshot
from haptic_topology.dynamics.constraints import PenaltyDirection
from haptic_topology.dynamics.contacts import ContactParams, LocalContacts
from haptic_topology.errors import MessageError
from haptic_topology.messages.check import (
    array,
    check_range,
    check_update_contacts,
    check_update_header,
    finite_scalar,
)
from haptic_topology.vocabulary import TaskSpace


def lmi_from_msg(msg: Any, task: TaskSpace, dof: int,
                 penalty_direction: PenaltyDirection = PenaltyDirection.NULLSPACE
                 ) -> LmiSnapshot:
    """The snapshot carried by ``msg``; sizes checked against the linkage's ``dof``, values
    against their ranges; ``penalty_direction``: the controller's own linkage setting (the
    message does not carry it) (the LMI factors the mass matrix: it must be symmetric positive
    definite; weights in [0, 1]; U orthogonal; ``L_c > 0``)."""
    seq, hand_input_seq = check_update_header(msg, task.dim, dof)
    m = task.dim
    mass = array(msg, 'mass_matrix', dof * dof).reshape(dof, dof)
    # np.allclose's test written out (its dispatch costs more than the test at 100 Hz)
    check_range(bool((np.abs(mass - mass.T) <= 1e-12 + 1e-9 * np.abs(mass.T)).all()), msg,
                'mass_matrix must be symmetric')
    try:
        np.linalg.cholesky(mass)
    except np.linalg.LinAlgError:
        raise MessageError('range', 'LmiUpdate.mass_matrix must be positive definite, got '
                           f'{mass.tolist()}') from None
    sv = array(msg, 'singular_values', min(m, dof))
    if not (sv >= 0.0).all():
        check_range(False, msg, f'singular_values must be >= 0, got {sv.tolist()}')
    u = array(msg, 'left_singular_vectors', m * m).reshape(m, m)
    eye = np.eye(m)
    check_range(bool((np.abs(u.T @ u - eye) <= 1e-6 + 1e-5 * eye).all()), msg,
                'left_singular_vectors must be orthonormal')
    weights = array(msg, 'constraint_weights', m)
    if not ((weights >= 0.0) & (weights <= 1.0)).all():
        check_range(False, msg, f'constraint_weights must be in [0, 1], got {weights.tolist()}')
    length = finite_scalar(msg, 'characteristic_length')
    if not length > 0.0:
        check_range(False, msg, f'characteristic_length must be > 0, got {length}')
    contacts = None
    fields = check_update_contacts(msg, dof)
    if fields is not None:
        points, normals, gaps, jac = fields
        contacts = LocalContacts(
            ContactParams(float(msg.contact_stiffness), float(msg.contact_damping),
                          float(msg.contact_friction), float(msg.contact_slip_velocity)),
            array(msg, 'q', dof), points, normals, gaps, jac, bool(msg.contact_local))
    return LmiSnapshot(
        seq=seq,
        hand_input_seq=hand_input_seq if hand_input_seq > 0 else -1,
        task=task,
        q=array(msg, 'q', dof), dq=array(msg, 'dq', dof),
        mass_matrix=mass,
        gravity=array(msg, 'gravity', dof),
        hand_jacobian=array(msg, 'hand_jacobian', m * dof).reshape(m, dof),
        singular_values=sv,
        left_vectors=u,
        weights=weights,
        constraint_count=int(msg.constraint_count),
        characteristic_length=length,
        hand_pose=array(msg, 'hand_pose', m), hand_twist=array(msg, 'hand_twist', m),
        penalty_direction=penalty_direction, contacts=contacts,
        contact_energy=float(getattr(msg, 'contact_energy', 0.0)))
