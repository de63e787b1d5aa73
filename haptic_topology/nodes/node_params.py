"""Parameters of device_driver, lmi_controller and ve_sim, declared once here (no rclpy).

The nodes declare them from these tables (:func:`haptic_topology.nodes.common.declare_spec`)
and :func:`haptic_topology.params.check_params_file` checks params files against the same
tables before rclpy reads them. ``config/haptic_topology.yaml`` lists every one. The
recorder declares its own (this process does not know them: only the structure of its
section is checked here).
"""

from __future__ import annotations

from haptic_topology.params import NodeParams, ParamSpec, specs

EXECUTORS = ('events', 'single_threaded')
MODES = ('penalty', 'acceleration_only')
FALLBACKS = ('zero', 'damping')
#: Upper end of the live penalty gains' range (N/(m kg), N s/(m kg)).
GAIN_MAX = 1.0e5

_SCENARIO = 'scenario name (config/scenarios) or YAML path'
_EXECUTOR = ParamSpec('executor', 'events', 'executor of the process', choices=EXECUTORS)
#: Real-time scheduling of the whole process (every thread, DDS's included).
SCHED_PRIORITY = ParamSpec(
    'sched_priority', 0, 'SCHED_FIFO priority 1-99 of the process (all its threads); 0 = '
    'normal scheduling. Needs CAP_SYS_NICE (root or an rtprio limit): without it a warning '
    'and normal scheduling', lo=0, hi=99)

DEVICE_DRIVER: NodeParams = specs(
    ParamSpec('scenario', 'fig8', f'{_SCENARIO}: device model, limits, initial pose and '
              'simulated user'),
    _EXECUTOR,
    SCHED_PRIORITY,
    ParamSpec('backend', 'sim_maglev', 'device backend: sim_maglev, hardware, module:Class, '
              'or an entry point of haptic_topology.device_backends'),
    ParamSpec('backend_options', '', "backend settings as a YAML/JSON mapping (e.g. '{port: "
              "/dev/ttyUSB0}'); empty for none"),
    ParamSpec('rate_hz', 1000.0, 'device cycle rate (Hz)', lo=10.0, hi=10000.0),
    ParamSpec('watchdog_timeout', 0.005, 'fade the output to the fallback when no fresh '
              'command came for this long (s): the oldest unanswered state is this old',
              lo=1e-4, hi=10.0),
    ParamSpec('watchdog_ramp', 0.05, 'time of a full fade between command and fallback, '
              'both ways (s)', lo=1e-3, hi=10.0),
    ParamSpec('watchdog_fallback', 'zero', 'output the watchdog fades to: zero, or damping '
              '(-watchdog_damping * device twist)', choices=FALLBACKS),
    ParamSpec('watchdog_damping', [0.0], 'damping of the damping fallback (N s/m, N m s/rad):'
              ' one value for every axis or task_dim values'),
    ParamSpec('min_subscribers', 1, 'ignore commands (device idle) until this many '
              'subscribers see the state topic (e.g. 2 with a recorder)', lo=0, hi=100),
    ParamSpec('wrench_limit', [0.0], "per-axis |u| limit (N, N m); [0.0] = the scenario's "
              'device.wrench_limit'),
)

LMI_CONTROLLER: NodeParams = specs(
    ParamSpec('scenario', 'fig8', f'{_SCENARIO}: linkage, gains, device inertia, LMI model'),
    _EXECUTOR,
    SCHED_PRIORITY,
    ParamSpec('mode', 'penalty', "control law: penalty (eq. 14) or acceleration_only "
              "(eq. 10); live; default: the scenario's", read_only=False, choices=MODES),
    ParamSpec('k_tc', 0.0, "penalty stiffness k_tc of eq. 13 (N/(m kg)); live; default: the "
              "scenario's", read_only=False, lo=0.0, hi=GAIN_MAX),
    ParamSpec('b_tc', 0.0, "penalty damping b_tc of eq. 13 (N s/(m kg)); live; default: the "
              "scenario's", read_only=False, lo=0.0, hi=GAIN_MAX),
    ParamSpec('max_dt', 0.05, 'longest measured period used for one LMI step (s); longer '
              'gaps (a paused device) are clipped', lo=1e-4, hi=1.0),
    ParamSpec('stale_after', 0.05, 'LMI update age (s) from which the model counts as stale '
              '(warning; the last constraint set is kept)', lo=1e-3, hi=60.0),
    ParamSpec('degrade_after', 0.6, 'LMI update age (s) from which the force fades to zero',
              lo=1e-3, hi=60.0),
    ParamSpec('resync_max_jump', 1.0, 'largest estimated force step (N, N m) a re-sync '
              'may cause at once: |K_pc dx| + |B_pc dv| + |M_d P (k_tc dx + b_tc dv)| '
              "(eq. 13-16), the update's VT hand against ours at the same time; beyond it "
              'the re-sync is held until the force has faded out', lo=0.0, hi=1e6),
    ParamSpec('resync_ramp', 0.2, 'time (s) of a full force fade out before / in after a '
              're-sync that may jump (stale model, restarted ve_sim or device)',
              lo=1e-3, hi=10.0),
)

VE_SIM: NodeParams = specs(
    ParamSpec('scenario', 'fig8', f'{_SCENARIO}: linkage, initial state, internal step, VT '
              'coupling'),
    _EXECUTOR,
    SCHED_PRIORITY,
    ParamSpec('update_period', 10, 'hand inputs per LMI update (10 at 1 kHz = 100 Hz); the '
              'scenario value is for the offline lock-step simulation', lo=1, hi=10000),
    ParamSpec('idle_update_rate_hz', 50.0, 'LMI updates per second while no hand input '
              'comes (start-up, controller stopped or restarting), so a controller can sync',
              lo=0.1, hi=1000.0),
    ParamSpec('max_hand_wrench', 1000.0, 'hand inputs with a hand or coupling wrench entry '
              'beyond this (N, N m) are rejected', lo=1e-3, hi=1e9),
    ParamSpec('viz_rate_hz', 30.0, 'rate of joint states and markers (Hz)', lo=0.1, hi=200.0),
    ParamSpec('frame_id', 'world', 'frame of the markers'),
)

#: Node name -> parameters known in this package's processes (recorder: its own).
KNOWN: dict[str, NodeParams | None] = {
    'device_driver': DEVICE_DRIVER,
    'lmi_controller': LMI_CONTROLLER,
    've_sim': VE_SIM,
    'recorder': None,
}
