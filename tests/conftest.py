"""Shared fixtures. Every test session gets a ROS_DOMAIN_ID of its own (unless ROS_DOMAIN_ID is set)."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = ROOT.parent / 'shared' / 'data'
SAMPLE_BAG = ROOT / 'bags' / 'sample_flight'

if not os.environ.get('ROS_DOMAIN_ID'):
    # A domain in 1..101 (ports below the ephemeral range) that nobody on this machine's network is on,
    # reserved until the session ends; child processes inherit it.
    from photogram_ros.nodes.ros_domain import reserve_test_domain
    os.environ['ROS_DOMAIN_ID'] = str(reserve_test_domain())
os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')


def shared_data(*parts) -> Path:
    """A path in ../shared/data: the test skips without it, or fails when PHOTOGRAM_ROS_REQUIRE_DATA is set
    (the real-data lane of .ci/run)."""
    p = SHARED_DATA.joinpath(*parts)
    if not p.exists():
        if os.environ.get('PHOTOGRAM_ROS_REQUIRE_DATA'):
            pytest.fail(f'shared data {p} not present (the real-data lane needs ../shared/data beside the clone)')
        pytest.skip(f'shared data {p} not present')
    return p


@pytest.fixture(scope='session')
def sample_bag() -> Path:
    if not SAMPLE_BAG.exists():
        pytest.fail(f'{SAMPLE_BAG} is missing: regenerate it with the command in bags/README.md')
    return SAMPLE_BAG


@pytest.fixture(scope='session')
def tiny_flight(tmp_path_factory) -> Path:
    """A short simulated flight (about 25 frames), generated once per test session."""
    from photogram_ros.sim.scenario import preset, simulate
    out = tmp_path_factory.mktemp('sim') / 'tiny'
    simulate(preset('tiny', fps=1.0, line_length_m=30.0), out)
    return out


@pytest.fixture
def rclpy_context():
    import rclpy
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    yield ctx
    rclpy.try_shutdown(context=ctx)


@pytest.fixture
def scratch(tmp_path) -> Path:
    yield tmp_path
    shutil.rmtree(tmp_path, ignore_errors=True)
