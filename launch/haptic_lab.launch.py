"""The haptic_topology node graph on a full ROS 2 Jazzy install (``ros2 launch``).

::

    ros2 launch haptic_topology haptic_lab.launch.py scenario:=fig8 mode:=penalty
    ros2 launch haptic_topology haptic_lab.launch.py layout:=separate clock:=lockstep
    ros2 launch haptic_topology haptic_lab.launch.py --show-args

Starts what ``haptic-topology run`` starts, with the same parameters: the processes of the
layout (``hosted``: ``recorder``, ``ve_sim`` and ``device_driver``, which runs
``lmi_controller`` in its loop thread; ``separate``: the four nodes as four processes;
``composed``: all four in one process; ``thread``: as ``hosted``, the cycle in a loop thread
of the driver's process instead of its loop process), each with the params file, then
``scenario``,
``clock``, the controller's ``mode``, the recorder's ``output``, ``device_driver``'s
``min_subscribers = 2`` (controller and recorder see the device before it engages),
``run_duration`` and ``host_controller`` (:func:`ros_arguments`).

Arguments (all optional): ``scenario`` (name or YAML file, default ``fig8``), ``mode``
(``penalty`` | ``acceleration_only``; empty: the scenario's), ``layout`` (``hosted`` |
``separate`` | ``composed`` | ``thread``), ``params_file`` (default: the installed
``share/haptic_topology/config/haptic_topology.yaml``), ``clock`` (``wall`` | ``lockstep``),
``duration`` (s of engaged loop after which the driver deactivates itself; empty: the
scenario's duration; ``0``: never), ``output`` (bag directory, must not exist; empty:
``bags/<scenario>_<timestamp>`` in the working directory), ``backend`` (the driver's device
backend; empty: the params file's).

Where it differs from ``haptic-topology run``, which is also the graph's lifecycle manager:
the driver configures and activates itself (``autostart``, the params file's default) and
engages once ``min_subscribers`` nodes see its states, instead of after the bringup saw the
recorder matched to every publisher (the recorder may miss the VE's first updates; the VE
repeats its state at ``idle_update_rate_hz`` until the loop runs); when ``duration`` has
passed the driver zeroes the output and goes ``inactive``, and the processes run until the
launch is stopped (Ctrl-C: the recorder closes its bag on SIGINT); the bag is not read back
(``haptic-topology analyze <bag>`` writes the trace, plot and summary).

Parameters are passed as ROS arguments in one list, the params file first: the last
assignment of a parameter wins, and ``Node(parameters=[file])`` would put the file after
``ros_arguments`` and undo every override. No ``name=`` either: ``-r __node:=`` renames every
node of a process, the hosted ``lmi_controller`` included.
"""

from __future__ import annotations

from pathlib import Path

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.launch_context import LaunchContext
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare

PACKAGE = 'haptic_topology'
#: Layout -> the executables (console scripts of setup.py) it starts, in the order of
#: ``haptic-topology run``.
LAYOUTS = {
    'hosted': ('recorder', 've_sim', 'device_driver'),
    'separate': ('recorder', 've_sim', 'lmi_controller', 'device_driver'),
    'composed': ('composed',),
    'thread': ('recorder', 've_sim', 'device_driver'),
}
MODES = ('', 'penalty', 'acceleration_only')
CLOCKS = ('wall', 'lockstep')


def ros_arguments(params_file: str, scenario: str, mode: str, layout: str, clock: str,
                  duration: float, output: str, backend: str) -> list[str]:
    """The ROS arguments of every process of the graph, as ``haptic-topology run`` passes
    them: the params file, then the overrides (``duration`` in s; empty ``mode``, ``output``
    and ``backend``: not overridden)."""
    host = 'false' if layout == 'separate' else 'true'
    args = ['--params-file', params_file,
            '-p', f'scenario:={scenario}', '-p', f'clock:={clock}',
            '-p', 'device_driver:min_subscribers:=2',
            '-p', f'device_driver:run_duration:={float(duration)!r}',
            '-p', f'device_driver:host_controller:={host}']
    if layout == 'thread':
        args += ['-p', 'device_driver:loop_process:=false']
    if mode:
        args += ['-p', f'lmi_controller:mode:={mode}']
    if output:
        args += ['-p', f'recorder:output:={output}']
    if clock == 'lockstep':
        args += ['-p', 'lmi_controller:use_sim_time:=true', '-p', 've_sim:use_sim_time:=true']
    if backend:
        args += ['-p', f'device_driver:backend:={backend}']
    return args


def _duration(text: str, scenario: str) -> float:
    """The ``duration`` argument (s); empty: the scenario's duration."""
    if not text.strip():
        from haptic_topology.sim.scenario import load_scenario

        return load_scenario(scenario).duration
    try:
        value = float(text)
    except ValueError:
        value = float('nan')
    if not value >= 0.0:
        raise ValueError(f'duration: expected seconds >= 0 (0: never stop), got {text!r}')
    return value


def _nodes(context: LaunchContext) -> list[Node]:
    """The processes of the chosen layout (the arguments resolved)."""
    scenario = LaunchConfiguration('scenario').perform(context)
    layout = LaunchConfiguration('layout').perform(context)
    if Path(scenario).suffix:               # a scenario file: the nodes may not share our cwd
        scenario = str(Path(scenario).resolve())
    args = ros_arguments(
        str(Path(LaunchConfiguration('params_file').perform(context)).resolve()),
        scenario,
        LaunchConfiguration('mode').perform(context),
        layout,
        LaunchConfiguration('clock').perform(context),
        _duration(LaunchConfiguration('duration').perform(context), scenario),
        LaunchConfiguration('output').perform(context),
        LaunchConfiguration('backend').perform(context))
    return [Node(package=PACKAGE, executable=executable, output='screen', ros_arguments=args)
            for executable in LAYOUTS[layout]]


def generate_launch_description() -> LaunchDescription:
    return LaunchDescription([
        DeclareLaunchArgument('scenario', default_value='fig8',
                              description='scenario name (config/scenarios) or YAML file'),
        DeclareLaunchArgument('mode', default_value='', choices=list(MODES),
                              description="control law; empty: the scenario's"),
        DeclareLaunchArgument('layout', default_value='hosted', choices=list(LAYOUTS),
                              description='hosted: controller in the driver process; '
                              'separate: one process per node; composed: one process'),
        DeclareLaunchArgument(
            'params_file',
            default_value=PathJoinSubstitution(
                [FindPackageShare(PACKAGE), 'config', 'haptic_topology.yaml']),
            description='ROS 2 params file of the four nodes'),
        DeclareLaunchArgument('clock', default_value='wall', choices=list(CLOCKS),
                              description='wall: real time; lockstep: simulated time'),
        DeclareLaunchArgument('duration', default_value='',
                              description="s of engaged loop, then the driver deactivates; "
                              "empty: the scenario's; 0: never"),
        DeclareLaunchArgument('output', default_value='',
                              description='bag directory (must not exist); empty: '
                              'bags/<scenario>_<timestamp>'),
        DeclareLaunchArgument('backend', default_value='',
                              description="device_driver backend; empty: the params file's"),
        OpaqueFunction(function=_nodes),
    ])
