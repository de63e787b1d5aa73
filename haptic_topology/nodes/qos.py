"""The rclpy QoS profiles of the graph's topics, built from the roles of
:mod:`haptic_topology.vocabulary`.

QoS of the graph (why):

============================  ================================  ===================================
topic                         QoS                               why
============================  ================================  ===================================
``haptic/device/state``       best effort, keep last 1          1 kHz; the newest state counts
``haptic/device/command``     best effort, keep last 1          1 kHz; a late command is useless,
                                                                the device applies the newest
``haptic/device/              best effort, keep last 1          ~30 Hz (either clock): a reader
state_sampled``                                                 takes the newest now and then
``haptic/hand_inputs``        reliable, keep last 500           ~100 Hz: one ``HandInputs`` per
                                                                VE update period with the 1 kHz
                                                                samples; the VE integrates every
                                                                one (zero-order hold between
                                                                them), a lost one would bend the
                                                                VT path. 500 batches: 5 s. Not on
                                                                the device's critical path, so a
                                                                retransmission costs nothing
``haptic/lmi/update``,        reliable, keep last 5000          ~100 Hz; each update re-syncs;
``haptic/ve/path``                                              the VT hand at every cycle
``/clock``                    best effort, keep last 1          lock-step only: simulated time
``haptic/joint_states``,      reliable, keep last 5             visualisation, ~30 Hz
``haptic/markers``,
``haptic/viz/...`` mirrors
``/tf``                       reliable, keep last 100           as tf2_ros broadcasts it
``/robot_description``        reliable, transient local,        once; a late subscriber gets it
                              keep last 1                       (as robot_state_publisher)
``/diagnostics``              reliable, keep last 10            1 Hz loop health
============================  ================================  ===================================

With ``clock: lockstep`` the state and command topics are reliable (keep last 10000): the
device steps only when the answer has come, so a lost message would stall the loop, and a bag
of the run must hold every state; the hand inputs keep 10000 batches too
(:func:`hand_inputs_qos`).

Why batches: a reliable 1 kHz stream with 5 s of history over UDP turned every gap (ve_sim
stopped for 1 s, or restarted) into a repair burst of hundreds of datagrams that overflowed
the socket buffer again, and the stream never recovered (fault test under load: 40697 inputs
lost against 11845 received). One message per VE update period carries the same samples in a
tenth of the messages, at the rate the VE consumes them anyway.

The recorder subscribes best effort with a deep queue (1000) to the best-effort topics and
reliable to the others, so it never slows a publisher down.
"""

from __future__ import annotations

from functools import cache

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from haptic_topology import vocabulary as vocab
from haptic_topology.device.topic_mapping import Reliability
from haptic_topology.vocabulary import Clock, QosRole


@cache
def profile(role: QosRole) -> QoSProfile:
    """The rclpy profile of ``role`` (one object per role)."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=role.depth,
        reliability=ReliabilityPolicy.RELIABLE if role.reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=(DurabilityPolicy.TRANSIENT_LOCAL if role.transient_local
                    else DurabilityPolicy.VOLATILE))


QOS_LOOP = profile(vocab.LOOP)
QOS_LOOP_LOCKSTEP = profile(vocab.LOOP_LOCKSTEP)
QOS_CLOCK = profile(vocab.CLOCK)
QOS_SAMPLED = profile(vocab.SAMPLED)
QOS_HAND_INPUTS = profile(vocab.HAND_INPUTS)
QOS_HAND_INPUTS_LOCKSTEP = profile(vocab.HAND_INPUTS_LOCKSTEP)
QOS_LMI = profile(vocab.LMI)
QOS_VIZ = profile(vocab.VIZ)
QOS_TF = profile(vocab.TF)
QOS_LATCHED = profile(vocab.LATCHED)
QOS_DIAGNOSTICS = profile(vocab.DIAGNOSTICS)
QOS_RECORD_BEST_EFFORT = profile(vocab.RECORD_BEST_EFFORT)
QOS_RECORD_RELIABLE = profile(vocab.RECORD_RELIABLE)

#: Topic -> QoS of its publisher (the recorder mirrors the reliability).
TOPIC_QOS: dict[str, QoSProfile] = {t: profile(r) for t, r in vocab.TOPIC_ROLES.items()}


def loop_qos(clock: Clock) -> QoSProfile:
    """QoS of the 1 kHz state/command topics under ``clock`` (see the table above)."""
    return profile(vocab.loop_role(clock))


def hand_inputs_qos(clock: Clock) -> QoSProfile:
    """QoS of ``haptic/hand_inputs`` under ``clock``: reliable either way (the VE must
    integrate every input); keep last 500 batches (5 s at 100 Hz), 10000 in lock-step."""
    return profile(vocab.hand_inputs_role(clock))


def publisher_qos(topic: str, clock: Clock) -> QoSProfile:
    """QoS the graph's publisher of ``topic`` (a key of :data:`TOPIC_QOS`) offers under
    ``clock`` (what the recorder mirrors and writes into the bag)."""
    return profile(vocab.publisher_role(topic, clock))
def topic_qos(reliability: Reliability) -> QoSProfile:
    """Keep last 1, volatile, with ``reliability``: only the newest sample counts."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                      reliability=(ReliabilityPolicy.RELIABLE
                                   if reliability is Reliability.RELIABLE
                                   else ReliabilityPolicy.BEST_EFFORT),
                      durability=DurabilityPolicy.VOLATILE)


