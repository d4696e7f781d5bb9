"""ament_python packaging for bearing_pose_estimation (used by colcon and by pip)."""
from glob import glob

from setuptools import find_packages, setup

package_name = 'bearing_pose_estimation'

# Every executable, in one place. `ros2 run bearing_pose_estimation <name>` finds these after a
# colcon build (setup.cfg puts them in lib/<package>); pip puts them in the venv's bin/.
console_scripts = [
    'bearing-pose = bearing_pose_estimation.cli.main:main',
    'estimator = bearing_pose_estimation.ros.estimator_node:main',
    'estimators = bearing_pose_estimation.ros.estimator_group:main',
    'simulator = bearing_pose_estimation.ros.simulator_node:main',
    'monitor = bearing_pose_estimation.ros.monitor_node:main',
    'fleet_markers = bearing_pose_estimation.ros.markers_node:main',
]

setup(
    name=package_name,
    version='0.1.0',
    # The top-level msg_defs/ folder is the subpackage bearing_pose_estimation.msg_defs through
    # the symlink bearing_pose_estimation/msg_defs -> ../msg_defs. A symlink, not a package_dir
    # mapping: `colcon build --symlink-install` and editable installs only handle real folders.
    packages=find_packages(exclude=['test', 'test.*', 'msg_defs', 'msg_defs.*']),
    data_files=[
        ('share/ament_index/resource_index/packages', [f'resource/{package_name}']),
        (f'share/{package_name}', ['package.xml']),
        (f'share/{package_name}/config', sorted(glob('config/*.yaml'))),
        (f'share/{package_name}/launch', sorted(glob('launch/*.launch.py'))),
    ],
    install_requires=['setuptools', 'numpy', 'scipy', 'PyYAML', 'matplotlib'],
    zip_safe=True,
    maintainer='bearing_pose_estimation maintainers',
    maintainer_email='maintainer@example.com',
    description='Distributed pose estimation for multi-agent systems from relative bearings.',
    license='Apache-2.0',
    tests_require=['pytest'],
    entry_points={'console_scripts': console_scripts},
)
