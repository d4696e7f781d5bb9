"""Packaging: package.xml, the colcon (ament_python) build, and the msg_defs subpackage mapping."""
import ast
import os
from pathlib import Path
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET

import pytest

PKG = 'bearing_pose_estimation'
# Top-level entries of the repo that are not part of the package source.
_NOT_SOURCE = {'.venv', '.git', 'build', 'install', 'log', 'results'}
_IMPORT_MSG_DEFS = 'import bearing_pose_estimation.msg_defs as m; print(m.__file__)'


def _copy_source(repo_root: Path, dest: Path) -> None:
    def ignore(directory, names):
        skip = {n for n in names if n in ('__pycache__', '.pytest_cache') or n.endswith('.egg-info')}
        if Path(directory) == repo_root:
            skip |= _NOT_SOURCE & set(names)
        return skip

    shutil.copytree(repo_root, dest, ignore=ignore, symlinks=True)


@pytest.fixture(scope='module', params=['copy', 'symlink-install'])
def colcon_install(request, repo_root, tmp_path_factory):
    """Build the package with colcon in a fresh workspace, as `colcon build` and as
    `colcon build --symlink-install` (what most ROS developers type); return the install prefix."""
    venv_bin = Path(sys.executable).parent
    colcon = venv_bin / 'colcon'
    assert colcon.exists(), (f'colcon is not installed beside {sys.executable}: '
                             'run scripts/dev.sh setup')
    ws = tmp_path_factory.mktemp('colcon_ws')
    _copy_source(repo_root, ws / 'src' / PKG)
    env = dict(os.environ, PATH=f"{venv_bin}{os.pathsep}{os.environ.get('PATH', '')}",
               COLCON_HOME=str(ws / 'colcon_home'))
    env.pop('PYTHONPATH', None)
    extra = ['--symlink-install'] if request.param == 'symlink-install' else []
    proc = subprocess.run([str(colcon), 'build', '--base-paths', 'src', *extra], cwd=ws, env=env,
                          capture_output=True, text=True, timeout=600)
    rc = proc.returncode
    assert rc == 0, f'colcon build failed:\n{proc.stdout}\n{proc.stderr}'
    return ws / 'install' / PKG


def _run_installed(prefix: Path, args, cwd: Path):
    """Run a command as a ROS user would: `source install/setup.bash`, then the command."""
    setup_bash = prefix.parent / 'setup.bash'
    assert setup_bash.is_file(), f'{setup_bash} missing (colcon-bash)'
    env = dict(os.environ)
    env.pop('PYTHONPATH', None)
    script = f'source "{setup_bash}" && exec "$@"'
    return subprocess.run(['bash', '-c', script, 'bash', *map(str, args)], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=120)


def test_colcon_build_installs_what_ros2_run_needs(colcon_install, repo_root, tmp_path):
    for name in ('bearing-pose', 'estimator', 'estimators', 'simulator', 'monitor'):
        exe = colcon_install / 'lib' / PKG / name  # where `ros2 run` looks
        assert exe.is_file(), f'{exe} missing: setup.cfg [install] install_scripts'
        assert os.access(exe, os.X_OK)
    exe = colcon_install / 'lib' / PKG / 'bearing-pose'
    share = colcon_install / 'share' / PKG
    assert (share / 'package.xml').is_file()
    assert (colcon_install / 'share' / 'ament_index' / 'resource_index' / 'packages' / PKG).is_file()
    configs = sorted(p.name for p in (repo_root / 'config').glob('*.yaml'))
    installed = sorted(p.name for p in (share / 'config').glob('*.yaml'))
    assert installed == configs
    # `ros2 launch bearing_pose_estimation fleet.launch.py` finds it here.
    assert (share / 'launch' / 'fleet.launch.py').is_file()

    # What `ros2 run bearing_pose_estimation bearing-pose --help` runs, with the install on the path.
    proc = _run_installed(colcon_install, [str(exe), '--help'], cwd=tmp_path)
    rc = proc.returncode
    assert rc == 0, f'bearing-pose --help failed:\n{proc.stdout}\n{proc.stderr}'
    assert proc.stdout.strip()


def test_package_xml(repo_root):
    root = ET.parse(repo_root / 'package.xml').getroot()
    assert root.get('format') == '3'
    assert root.findtext('name') == PKG
    assert root.findtext('export/build_type') == 'ament_python'
    exec_depends = {e.text for e in root.iter('exec_depend')}
    # Every third-party module the package imports is declared, and little else: rosdep keys
    # for Python libraries are python3-<name> (python3-yaml for PyYAML).
    imported = set()
    for path in [*(repo_root / PKG).rglob('*.py'), *(repo_root / 'msg_defs').glob('*.py')]:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                imported |= {a.name.split('.')[0] for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                imported.add(node.module.split('.')[0])
    third_party = imported - set(sys.stdlib_module_names) - {PKG}
    # rosbags (run --record, export-tum) has no rosdep key we know of: pip, requirements.txt.
    pip_only = {'rosbags'}
    requirements = (repo_root / 'requirements.txt').read_text()
    assert all(f'\n{m}==' in requirements for m in pip_only)
    ros = ('rclpy', '_msgs', '_interfaces')
    packages = {'tf2_ros': 'tf2_ros_py'}   # ROS packages named otherwise than their module
    needed = {packages.get(m, m if m.endswith(ros) else f'python3-{m}')
              for m in third_party - pip_only}
    assert needed <= exec_depends
    assert exec_depends == needed   # std_msgs: /monitor/ready (and every stamped Header)


def test_the_math_core_imports_no_rclpy():
    """Everything but the nodes (``ros/``) and the wire format (``msg_defs``) is usable without
    ROS: the math core (SO(3), estimators, scenarios, graph checks, batch simulator, netsim),
    the studies and the command line. Importing every such module must not import rclpy."""
    import pkgutil

    import bearing_pose_estimation as pkg

    core = [m.name for m in pkgutil.walk_packages(pkg.__path__, f'{PKG}.')
            if not m.name.startswith((f'{PKG}.ros', f'{PKG}.msg_defs'))]
    assert {f'{PKG}.core.so3', f'{PKG}.runtime.agent', f'{PKG}.sim.batch',
            f'{PKG}.cli.main'} <= set(core)
    code = ('import sys; ' + '; '.join(f'import {m}' for m in core)
            + "; print(sorted(m for m in sys.modules if m.split('.')[0] == 'rclpy'))")
    proc = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == '[]'


def test_msg_defs_imports_from_repo(repo_root):
    import bearing_pose_estimation.msg_defs as msg_defs

    assert Path(msg_defs.__file__).resolve() == repo_root / 'msg_defs' / '__init__.py'


def test_msg_defs_imports_from_editable_install_outside_repo(repo_root, tmp_path):
    env = dict(os.environ)
    env.pop('PYTHONPATH', None)
    proc = subprocess.run([sys.executable, '-c', _IMPORT_MSG_DEFS], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert Path(proc.stdout.strip()).resolve() == repo_root / 'msg_defs' / '__init__.py'


def test_msg_defs_imports_from_colcon_install(colcon_install, tmp_path):
    proc = _run_installed(colcon_install, [sys.executable, '-c', _IMPORT_MSG_DEFS], cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    # From the workspace (install/, or build/ for --symlink-install), not from this checkout.
    workspace = colcon_install.parent.parent
    assert Path(proc.stdout.strip()).resolve().is_relative_to(workspace.resolve()), proc.stdout


@pytest.mark.dds
def test_colcon_built_estimator_talks_dds(colcon_install, tmp_path):
    """`ros2 run bearing_pose_estimation estimator --ros-args -r __ns:=/agent_1 -p
    scenario_file:=...` from the colcon install: once its inputs have publishers and its
    outputs the readers of its listeners (here stand-ins for them) it announces its t0
    estimate (leader agent_1: its true pose) in frame `world`, and exits 0 on Ctrl-C."""
    import signal

    import numpy as np

    from bearing_pose_estimation import msg_defs as wire
    from bearing_pose_estimation.msg_defs import cdr
    from bearing_pose_estimation.ros.wiring import listener_counts
    from bearing_pose_estimation.scenario import load_scenario
    from ros_helpers import observer

    exe = colcon_install / 'lib' / PKG / 'estimator'
    scenario = colcon_install / 'share' / PKG / 'config' / 'paper_8_agents.yaml'
    setup_bash = colcon_install.parent / 'setup.bash'
    env = dict(os.environ)
    env.pop('PYTHONPATH', None)
    script = (f'source "{setup_bash}" && exec "{exe}" --ros-args -r __ns:=/agent_1 '
              f'-p scenario_file:={scenario} -p use_sim_time:=true')
    proc = subprocess.Popen(['bash', '-c', script], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    try:
        with observer() as obs:
            obs.subscribe(wire.PoseStamped, '/agent_1/estimate', wire.ESTIMATE_QOS)
            pubs = [obs.node.create_publisher(wire.Imu, '/agent_1/imu', wire.SIM_PUB_QOS),
                    obs.node.create_publisher(wire.PointCloud2, '/agent_1/bearings',
                                              wire.SIM_PUB_QOS),
                    obs.node.create_publisher(wire.PoseStamped, '/agent_1/known_pose',
                                              wire.SIM_PUB_QOS)]
            s = load_scenario(scenario)   # the topics of its method's channels, their types
            types = {wire.ESTIMATE: wire.PoseStamped,
                     **{c.topic: wire.channel_type(c) for c in s.estimator().sends}}
            for (agent, topic), n in listener_counts(s).items():
                for _ in range(n if agent == 'agent_1' else 0):   # agent_1's listeners
                    obs.node.create_subscription(types[topic], wire.topic(agent, topic),
                                                 lambda _: None, wire.ESTIMATE_QOS)
            got = obs.spin_until(lambda: bool(obs.messages['/agent_1/estimate']), timeout=60)
            assert all(p.get_subscription_count() == 1 for p in pubs)
            assert got, 'no estimate from the installed estimator'
        msg = obs.messages['/agent_1/estimate'][0]
        assert msg.header.frame_id == 'world'
        t, R, p = cdr.decode_pose_raw(msg)
        assert t == 0.0
        np.testing.assert_allclose(p, [0.0, 0.0, 0.0])
        np.testing.assert_allclose(R, np.eye(3), atol=1e-12)
    finally:
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=30)
    assert proc.returncode == 0, out
    assert 'agent_1 (id 1, leader) at 100 Hz' in out


def test_one_version_a_license_and_bearing_pose_version(repo_root, capsys):
    """package.xml, setup.py and the package say the same version, which `bearing-pose
    --version` prints; the Apache-2.0 that package.xml and setup.py declare is in LICENSE."""
    from bearing_pose_estimation import __version__
    from bearing_pose_estimation.cli.main import main

    root = ET.parse(repo_root / 'package.xml').getroot()
    setup = ast.parse((repo_root / 'setup.py').read_text())
    setup_kw = {kw.arg: kw.value for node in ast.walk(setup) if isinstance(node, ast.Call)
                for kw in node.keywords}
    assert root.findtext('version') == ast.literal_eval(setup_kw['version']) == __version__
    assert root.findtext('license') == ast.literal_eval(setup_kw['license']) == 'Apache-2.0'
    text = (repo_root / 'LICENSE').read_text()
    assert 'Apache License' in text and 'Version 2.0, January 2004' in text
    with pytest.raises(SystemExit) as info:
        main(['--version'])
    assert info.value.code == 0
    assert capsys.readouterr().out.strip() == f'bearing-pose {__version__}'
