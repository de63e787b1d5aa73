"""Haptic device models and simulated users (eq. 9)."""

from haptic_topology.device.maglev import DeviceParams, MaglevModel, saturate
from haptic_topology.device.users import (
    ConstantWrenchUser,
    SpringDamperUser,
    TargetPath,
    UserModel,
    user_from_config,
)
from haptic_topology.vocabulary import DeviceStatus

__all__ = ['ConstantWrenchUser', 'DeviceParams', 'DeviceStatus', 'MaglevModel',
           'SpringDamperUser', 'TargetPath', 'UserModel', 'saturate', 'user_from_config']
