"""Control laws (eq. 10, eq. 14 with eq. 13) and the local model of interaction (eq. 17-20)."""

from haptic_topology.control.controller import CycleOutput, HapticController
from haptic_topology.control.laws import (
    ControlGains,
    acceleration_control,
    control_wrench,
    coordination_wrench,
    penalty_acceleration,
    penalty_control,
)
from haptic_topology.control.lmi import LmiModel, LmiSnapshot, LocalModel
from haptic_topology.vocabulary import ControlMode

__all__ = ['ControlGains', 'ControlMode', 'CycleOutput', 'HapticController', 'LmiModel',
           'LmiSnapshot', 'LocalModel', 'acceleration_control', 'control_wrench',
           'coordination_wrench', 'penalty_acceleration', 'penalty_control']
