"""The fleet of `bearing-pose run`, for `ros2 launch` on a full ROS 2 Jazzy install:

    ros2 launch bearing_pose_estimation fleet.launch.py scenario:=/path/to/scenario.yaml \
        [out:=results/<name>_launch] [duration:=0] [fleet_namespace:=team_a]

One estimator per agent (namespace /<agent>), the monitor and the simulator, with the
parameter files `bearing-pose run` writes (into `out`/params) and the same remappings
(bearing_pose_estimation.plan.processes.launch_nodes: one plan for both). DDS discovery stays on
loopback; the domain is your ROS_DOMAIN_ID. Unlike `bearing-pose run`, nothing stops the fleet
when the monitor is done: Ctrl-C.
"""
from pathlib import Path

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction, SetEnvironmentVariable
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

PACKAGE = 'bearing_pose_estimation'


def _fleet(context, *args, **kwargs):
    from bearing_pose_estimation.plan import processes as plan
    from bearing_pose_estimation.scenario import load_scenario

    def value(name: str) -> str:
        return LaunchConfiguration(name).perform(context)

    scenario_file = Path(value('scenario')).resolve()
    scenario = load_scenario(scenario_file)
    out = Path(value('out') or f'results/{scenario.name}_launch').resolve()
    duration = float(value('duration') or 0.0) or scenario.duration
    cfg = plan.RunConfig(scenario_file=scenario_file, out_dir=out, duration=duration,
                         domain_id=0, fleet_namespace=value('fleet_namespace'))
    cfg.logs_dir.mkdir(parents=True, exist_ok=True)
    specs = plan.plan_processes(scenario, plan.write_params(scenario, cfg), cfg.logs_dir,
                                lambda name: Path(name), fleet=cfg.fleet_namespace)
    nodes = []
    for n in plan.launch_nodes(specs):
        parameters: list = list(n.parameter_files)
        if n.parameters:
            parameters.append(dict(n.parameters))
        nodes.append(Node(package=PACKAGE, executable=n.executable, name=n.name,
                          namespace=n.namespace, remappings=list(n.remappings),
                          parameters=parameters, arguments=list(n.arguments), output='screen'))
    return nodes


def generate_launch_description() -> LaunchDescription:
    return LaunchDescription([
        DeclareLaunchArgument('scenario', description='scenario YAML file'),
        DeclareLaunchArgument('out', default_value='',
                              description='output directory (default results/<name>_launch)'),
        DeclareLaunchArgument('duration', default_value='0',
                              description="simulated time [s]; 0: the scenario's"),
        DeclareLaunchArgument('fleet_namespace', default_value='',
                              description='run every node and topic under /<it>/ (default: '
                                          'none)'),
        SetEnvironmentVariable('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST'),
        OpaqueFunction(function=_fleet),
    ])
