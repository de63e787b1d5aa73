"""Haptic device models and simulated users (eq. 9)."""

from haptic_topology.device.maglev import DeviceParams, DeviceStatus, MaglevModel, saturate
from haptic_topology.device.users import (
    ConstantWrenchUser,
    SpringDamperUser,
    TargetPath,
    UserModel,
    user_from_config,
)

__all__ = ['ConstantWrenchUser', 'DeviceParams', 'DeviceStatus', 'MaglevModel',
           'SpringDamperUser', 'TargetPath', 'UserModel', 'saturate', 'user_from_config']
