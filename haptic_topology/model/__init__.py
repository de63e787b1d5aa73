"""Linkage description (YAML or URDF) -> Pinocchio model with a grasp frame."""

from haptic_topology.model.build import LinkageModel, build_model
from haptic_topology.model.linkage import (
           CollisionShape,
           ConstraintSettings,
           JointType,
           Linkage,
           LinkSpec,
           PenaltyDirection,
           linkage_from_dict,
           load_linkage,
           reach,
           serial_chain,
           to_dict,
)
from haptic_topology.vocabulary import TaskSpace

__all__ = ['CollisionShape', 'ConstraintSettings', 'JointType', 'LinkSpec', 'Linkage',
           'LinkageModel',
           'PenaltyDirection', 'TaskSpace', 'build_model', 'linkage_from_dict', 'load_linkage',
           'reach', 'serial_chain', 'to_dict']
