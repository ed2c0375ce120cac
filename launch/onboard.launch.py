"""ros2 launch photogram_ros onboard.launch.py [params_file:=FILE] [namespace:=/drone1] [nodes:=a,b]

The mapping graph as `photogram-ros run --separate` starts it: one process per node (the console
scripts of setup.py), each given its part of one ROS 2 parameter file (default: the installed
config/onboard_rtk.yaml). The camera node starts only when the file has a camera_node section, as
with `run`. The parameters go to each node directly rather than as the file, so a namespace does not
hide the file's `mavlink_node:` sections from the nodes. The survey products are not written when the
nodes stop (that is `run`'s job): `photogram-ros export MAPDIR --densify --crs EPSG:XXXX --out DIR`.

Frames (docs/nodes.md, "The frame tree"): bundle_node publishes /tf and /tf_static where tf2_msgs imports,
prefixed with the namespace without its slashes (namespace:=/drone1 gives drone1/odom ...):

    map -> <ns>/odom (static, identity) -> <ns>/base_link (each adjusted pose) -> <ns>/camera_optical (static)
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from photogram_ros.errors import ConfigError
from photogram_ros.nodes.graph import NODES, roles_for
from photogram_ros.params import load_params_file

PACKAGE = 'photogram_ros'
DEFAULT_PARAMS = 'onboard_rtk.yaml'


def node_parameters(sections: dict, executable: str) -> dict:
    """One node's values: the file's `**` section, then each section named after the node (any namespace)."""
    values = dict(sections.get('**', {}))
    for name, section in sections.items():
        if name.split('/')[-1] == executable:
            values.update(section)
    return values


def mapping_nodes(context) -> list:
    params_file = LaunchConfiguration('params_file').perform(context)
    namespace = LaunchConfiguration('namespace').perform(context)
    roles = [r.strip() for r in LaunchConfiguration('nodes').perform(context).split(',') if r.strip()]
    roles = roles or list(roles_for(params_file))
    unknown_roles = [r for r in roles if r not in NODES]
    if unknown_roles:
        raise ConfigError(f'nodes:={",".join(unknown_roles)}: choose from {",".join(NODES)}')
    sections = load_params_file(params_file)
    executables = [script for _, _, script in NODES.values()]
    stray = [s for s in sections if s != '**' and s.split('/')[-1] not in executables]
    if stray:
        raise ConfigError(f'{params_file}: sections {stray} name no node of photogram_ros; nodes are {executables}')
    return [Node(package=PACKAGE, executable=NODES[r][2], name=NODES[r][2], namespace=namespace,
                 parameters=[node_parameters(sections, NODES[r][2])], output='screen', emulate_tty=True)
            for r in roles]


def generate_launch_description():
    default_params = os.path.join(get_package_share_directory(PACKAGE), 'config', DEFAULT_PARAMS)
    return LaunchDescription([
        DeclareLaunchArgument('params_file', default_value=default_params,
                              description='ROS 2 parameter file for every node (config/onboard_gps.yaml for 3D GNSS)'),
        DeclareLaunchArgument('namespace', default_value='', description='namespace of this drone, e.g. /drone1'),
        DeclareLaunchArgument('nodes', default_value='',
                              description='comma-separated subset of ' + ','.join(NODES)
                              + ' (default: all but camera; camera too when the file has a camera_node section)'),
        OpaqueFunction(function=mapping_nodes),
    ])
