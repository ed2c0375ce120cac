from glob import glob

from setuptools import find_packages, setup

package_name = 'photogram_ros'

NODES = {
    'camera_node': 'photogram_ros.nodes.camera_node:main',
    'mavlink_node': 'photogram_ros.nodes.mavlink_node:main',
    'tracker_node': 'photogram_ros.nodes.tracker_node:main',
    'bundle_node': 'photogram_ros.nodes.bundle_node:main',
    'stereo_node': 'photogram_ros.nodes.stereo_node:main',
    'map_node': 'photogram_ros.nodes.map_node:main',
    'player_node': 'photogram_ros.nodes.player_node:main',
}

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['tests', 'tests.*', 'bench']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', glob('config/*.yaml')),
        ('share/' + package_name + '/launch', glob('launch/*.launch.py')),
    ],
    # The ground station's web page (Leaflet shipped with the package: it works offline).
    package_data={'photogram_ros': ['web/static/*.html', 'web/static/*.js', 'web/static/*.css',
                                    'web/static/vendor/leaflet/*', 'web/static/vendor/leaflet/images/*']},
    install_requires=['setuptools'],
    # colcon runs pytest (not unittest, which finds no test here) only when pytest is a test dependency.
    extras_require={'test': ['pytest']},
    zip_safe=False,   # the web page's files are read from the package folder
    maintainer='photogram_ros developers',
    maintainer_email='dev@photogram-ros.invalid',
    description='Onboard photogrammetric mapping for drones (ROS 2)',
    license='Apache-2.0',
    python_requires='>=3.10',
    entry_points={
        'console_scripts': ['photogram-ros = photogram_ros.cli:main']
        + [f'{name} = {target}' for name, target in NODES.items()],
    },
)
