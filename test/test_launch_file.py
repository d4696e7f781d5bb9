"""The installed launch file, launch/fleet.launch.py, without launch_ros (not installable
here): stand-ins for launch and launch_ros record what it builds, and the nodes must be the
processes `bearing-pose run` plans, with the same executables, names, namespaces, remappings
and parameter files (plan.processes.launch_nodes: one plan for both)."""
from __future__ import annotations

import importlib.util
import sys
import types
from pathlib import Path

import pytest

from bearing_pose_estimation.plan import processes as plan
from bearing_pose_estimation.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / 'config' / 'paper_8_agents.yaml'


class _Recorded:
    def __init__(self, *args, **kwargs):
        self.args, self.kwargs = args, kwargs


class _Config:
    values: dict[str, str] = {}

    def __init__(self, name):
        self.name = name

    def perform(self, context):
        return self.values[self.name]


@pytest.fixture()
def launch_file(monkeypatch):
    """The launch file's module, imported against stand-in launch and launch_ros packages."""
    fake = {name: types.ModuleType(name) for name in
            ('launch', 'launch.actions', 'launch.substitutions', 'launch_ros',
             'launch_ros.actions')}
    fake['launch'].LaunchDescription = lambda actions: list(actions)
    for cls in ('DeclareLaunchArgument', 'OpaqueFunction', 'SetEnvironmentVariable'):
        setattr(fake['launch.actions'], cls, type(cls, (_Recorded,), {}))
    fake['launch.substitutions'].LaunchConfiguration = _Config
    fake['launch_ros.actions'].Node = type('Node', (_Recorded,), {})
    for name, module in fake.items():
        monkeypatch.setitem(sys.modules, name, module)
    spec = importlib.util.spec_from_file_location('fleet_launch',
                                                  ROOT / 'launch' / 'fleet.launch.py')
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_launch_file_starts_what_run_plans(launch_file, tmp_path):
    actions = launch_file.generate_launch_description()
    kinds = [type(a).__name__ for a in actions]
    assert kinds.count('DeclareLaunchArgument') == 4 and 'OpaqueFunction' in kinds
    env = next(a for a in actions if type(a).__name__ == 'SetEnvironmentVariable')
    assert env.args == ('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    fleet = next(a for a in actions if type(a).__name__ == 'OpaqueFunction').kwargs['function']
    out = tmp_path / 'out'
    _Config.values = {'scenario': str(PAPER), 'out': str(out), 'duration': '5',
                      'fleet_namespace': ''}
    nodes = [n.kwargs for n in fleet(context=None)]

    scenario = load_scenario(PAPER)
    cfg = plan.RunConfig(scenario_file=PAPER, out_dir=out, duration=5.0, domain_id=0)
    specs = plan.plan_processes(scenario, plan.write_params(scenario, cfg), cfg.logs_dir,
                                lambda name: Path(name))
    assert len(nodes) == len(specs) == 10
    for node, spec in zip(nodes, specs):
        argv = list(spec.argv)
        assert node['package'] == 'bearing_pose_estimation'
        assert node['executable'] == argv[0]
        assert node['namespace'] == (spec.name if spec.kind == 'estimator' else None)
        assert node['name'] == spec.kind
        ros = argv[argv.index('--ros-args') + 1:]
        pairs = list(zip(ros[::2], ros[1::2]))
        assert node['parameters'] == [v for f, v in pairs if f == '--params-file']
        assert all(Path(f).is_file() for f in node['parameters'])   # written for the launch
        remaps = [tuple(v.split(':=')) for f, v in pairs if f == '-r'
                  and not v.startswith('__')]
        assert node['remappings'] == remaps
    leaders = [n for n in nodes if n['remappings'] == [('known_pose', 'ground_truth')]]
    assert [n['namespace'] for n in leaders] == list(scenario.leaders)


def test_the_launch_file_takes_a_fleet_namespace(launch_file, tmp_path):
    """fleet_namespace:=team_a: every node under /team_a, the clock remapped to its own."""
    actions = launch_file.generate_launch_description()
    fleet = next(a for a in actions if type(a).__name__ == 'OpaqueFunction').kwargs['function']
    _Config.values = {'scenario': str(PAPER), 'out': str(tmp_path / 'out'), 'duration': '5',
                      'fleet_namespace': 'team_a'}
    nodes = [n.kwargs for n in fleet(context=None)]
    assert {n['namespace'] for n in nodes} == {'team_a'} | {
        f'team_a/{a.name}' for a in load_scenario(PAPER).agents}
    assert all(('/clock', '/team_a/clock') in n['remappings'] for n in nodes)
