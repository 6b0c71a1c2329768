from glob import glob
import os
from pathlib import Path

from setuptools import find_packages, setup

package_name = 'feeder_sim'

ros = ['ros-jazzy-rclpy', 'ros-jazzy-common-interfaces', 'ros-jazzy-rmw-fastrtps-cpp',
       'ros-jazzy-ament-index-python']
replay = ['rerun-sdk==0.41.0']
# the rosidl generators and ament_cmake from PyPI that interfaces/build.py builds the node's
# part services with (one list, also for colcon workspaces: interfaces/requirements.txt)
interfaces = [line.strip() for line in
              (Path(__file__).resolve().parent / 'interfaces' / 'requirements.txt').read_text()
              .splitlines() if line.strip() and not line.startswith('#')]
# design studies: trials on Dask, the Parquet table
study = ['dask[distributed]>=2024.6', 'pyarrow>=15']
# colcon from PyPI: the packaging test builds this package in a workspace as ROS users do.
colcon = ['colcon-core', 'colcon-ros', 'colcon-python-setup-py', 'colcon-library-path',
          'colcon-bash', 'ros-jazzy-ament-package']

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'benchmarks']),
    # what a first run compiles, for the helper process that shares the compile
    package_data={package_name: ['compiled/plans/*.json']},
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        (os.path.join('share', package_name, 'config'), glob('config/*.yaml')),
        (os.path.join('share', package_name, 'config', 'studies'),
         glob('config/studies/*.yaml')),
    ],
    python_requires='>=3.11',
    # numba below 0.69: feeder_sim.compiled patches numba internals (the codegen library and
    # CPU context for the deferred codegen and inlined reference counts, the dispatcher's
    # compile for the compile locks, the cache locators), tested on numba 0.68. A release that
    # moves them turns a patch off (slower, same results); one that changes what they rely on
    # may go unnoticed. Raise the bound once test_kernel_cache, test_compile_ahead and
    # test_fingerprint pass on the new minor version.
    install_requires=['setuptools', 'numpy>=1.26', 'scipy>=1.11', 'numba>=0.60,<0.69',
                      'pyyaml>=6', 'matplotlib>=3.8', 'mcap>=1.2', 'mcap-ros2-support>=0.5',
                      'simpleeval>=1.0', 'tqdm>=4.66'],
    extras_require={
        'ros': ros,
        'replay': replay,
        'interfaces': interfaces,
        # a peer engine for `feeder-sim accuracy` (same cases, same plot)
        'peers': ['pymunk>=6.6'],
        'study': study,
        'test': ros + replay + interfaces + study + colcon + ['pymunk>=6.6', 'pytest>=8',
                                                 'pytest-timeout>=2.3', 'hypothesis>=6.100',
                                                 'ruff>=0.6'],
    },
    zip_safe=True,
    maintainer='feeder_sim maintainers',
    maintainer_email='maintainers@feeder-sim.invalid',
    description='2D rigid-body simulation of vibratory parts feeders with frictional impulses',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'feeder-sim = feeder_sim.cli:main',
            'sim_node = feeder_sim.ros.entry:main',
        ],
    },
)
