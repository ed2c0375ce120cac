"""Which DDS domain a session joins: the UDP port check that keeps test sessions and replays apart across
processes, users and containers that share one machine's network."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from photogram_ros.errors import ConfigError
from photogram_ros.nodes import ros_domain

ROOT = Path(__file__).resolve().parents[1]


def _bind(port: int) -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(('127.0.0.1', port))
    return s


def _block(domain: int) -> range:
    """Fast DDS's ports of `domain`, by its documented formula (7400 + 250 x domain, 250 of them)."""
    return range(7400 + 250 * domain, 7400 + 250 * domain + 250)


def test_udp_tables_are_read_as_fast_dds_port_blocks(tmp_path):
    """A hand-written /proc/net/udp: ports 17910 (domain 42, participant 0) and 7650 (domain 1's first),
    an IPv6 row of domain 230, and an ephemeral port and a torn row that count nothing."""
    v4 = tmp_path / 'udp'
    v4.write_text('  sl  local_address rem_address   st\n'
                  f'   0: 0100007F:{17910:04X} 00000000:0000 07\n'
                  f'   1: 00000000:{7650:04X} 00000000:0000 07\n'
                  f'   2: 00000000:{7399:04X} 00000000:0000 07\n'
                  '   3: garbage\n')
    v6 = tmp_path / 'udp6'
    v6.write_text('  sl  local_address\n'
                  f'   0: 00000000000000000000000000000000:{7400 + 250 * 230 + 17:04X} 000:0000 07\n')
    assert ros_domain.domains_in_use((str(v4), str(v6), str(tmp_path / 'missing'))) == {1, 42, 230}


def test_a_live_participant_marks_its_domain_in_use(rclpy_context):
    """The session's own nodes (rclpy, Fast DDS) bind ports of its domain: the check sees them."""
    from rclpy.node import Node
    mine = int(os.environ['ROS_DOMAIN_ID'])
    node = Node('domain_probe', context=rclpy_context)
    try:
        assert mine in ros_domain.domains_in_use()
    finally:
        node.destroy_node()


def test_a_test_session_skips_busy_domains_and_reserves_its_own():
    """Of two domains, one with a socket bound in its block: the free one is taken and its port bound,
    so a second session (another process) finds none left and says so."""
    free = [d for d in range(60, 100) if d not in ros_domain.domains_in_use()][:2]
    busy, want = free
    holder = _bind(_block(busy)[123])
    try:
        assert ros_domain.reserve_test_domain(free) == want
        assert want in ros_domain.domains_in_use()
        code = ('from photogram_ros.nodes.ros_domain import reserve_test_domain; '
                f'print(reserve_test_domain([{busy}, {want}]))')
        res = subprocess.run([sys.executable, '-c', code], cwd=ROOT, capture_output=True, text=True, timeout=60,
                             env={**os.environ, 'PYTHONPATH': str(ROOT)})
        assert res.returncode == 1 and 'ConfigError' in res.stderr and 'ROS_DOMAIN_ID' in res.stderr, res.stderr
    finally:
        holder.close()


def test_replays_skip_a_domain_another_container_is_on():
    """A replay's own domain: every one of 215..232 but one has a port bound (as a ROS 2 system in
    another container on this network would): the replay takes the one left, though no lock file says
    the others are held."""
    code = 'from photogram_ros.nodes.ros_domain import own_domain; print(own_domain())'

    def replay_domain():
        return subprocess.run([sys.executable, '-c', code], cwd=ROOT, capture_output=True, text=True, timeout=60,
                              env={**os.environ, 'PYTHONPATH': str(ROOT)})

    first = replay_domain()                 # free of locks and ports; freed again as its process ended
    left = int(first.stdout)
    held = [_bind(_block(d)[10]) for d in ros_domain.OWN_DOMAINS
            if d != left and d not in ros_domain.domains_in_use()]
    try:
        second = replay_domain()
        assert second.stdout.strip() == str(left), second.stderr
        held.append(_bind(_block(left)[10]))
        with pytest.raises(ConfigError, match='DDS participant'):
            ros_domain.own_domain()
    finally:
        for s in held:
            s.close()
