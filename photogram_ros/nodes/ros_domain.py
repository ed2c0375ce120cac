"""Which DDS domain a process joins: the user's ROS_DOMAIN_ID checked, or a domain of its own.

- `check_domain_env()`: ROS_DOMAIN_ID must be an integer 0..232 (Fast DDS computes its UDP ports as
  7400 + 250 x domain: 233 and above give ports past 65535, which it refuses with a raw "port number
  is too high" on every node). A ConfigError (one line, exit 2) otherwise.
- `own_domain()`: an offline replay needs nobody else on its graph, and must not feed an old flight
  into anyone's (two replays from two terminals, a replay on a ground-station PC beside a flying
  drone). It takes a domain of its own among 215..232, whose ports lie above Linux's ephemeral port range
  (32768..60999, where the OS hands out ports that would collide with them) as those of 0..101 lie below
  it, and apart from the domains a test session picks (1..101): a domain is taken by holding an exclusive flock(2) on a file in the temporary
  folder for the life of the process, so two replays on one machine never share one, and a replay
  killed with -9 frees its domain with its end. `replay --domain N` holds N the same way
  (`shared_domain`): a second replay on N is refused. A domain whose UDP ports are bound on this
  machine's network (a ROS 2 system already on it, or a session in another container sharing the
  network, where the lock files are not shared) is skipped too (`domains_in_use`).
- `reserve_test_domain()`: a test session's domain among 1..101, chosen free by the same port check
  and reserved for the life of the session by binding one port of its block, so that a session started
  later on this machine's network sees it taken.
"""

from __future__ import annotations

import fcntl
import os
import random
import socket
import tempfile
from collections.abc import Sequence
from pathlib import Path

from photogram_ros.errors import ConfigError

DOMAIN_MAX = 232
OWN_DOMAINS = range(215, DOMAIN_MAX + 1)
TEST_DOMAINS = range(1, 102)
PORT_BASE = 7400             # Fast DDS: domain d owns UDP ports PORT_BASE + PORTS_PER_DOMAIN x d and the next 249
PORTS_PER_DOMAIN = 250
_RESERVE_OFFSET = PORTS_PER_DOMAIN - 1   # participant 119's user port: the last of the block, the least used

_held: list = []   # lock file descriptors and reservation sockets, kept open for the life of the process


def parse_domain(value, where: str = 'ROS_DOMAIN_ID') -> int:
    """'42' -> 42; a ConfigError for anything but an integer 0..232."""
    try:
        d = int(str(value).strip())
    except ValueError:
        raise ConfigError(f'{where}={value!r} is not a number: a ROS 2 domain id is an integer 0 to '
                          f'{DOMAIN_MAX}') from None
    if not 0 <= d <= DOMAIN_MAX:
        raise ConfigError(f'{where}={d} is out of range: ROS 2 (Fast DDS) takes domain ids 0 to {DOMAIN_MAX} '
                          '(its UDP ports are 7400 + 250 x domain); set another ROS_DOMAIN_ID')
    return d


def check_domain_env() -> int | None:
    """The environment's ROS_DOMAIN_ID (None: not set, domain 0), checked."""
    value = os.environ.get('ROS_DOMAIN_ID', '')
    return parse_domain(value) if value.strip() else None


def _lock_path(domain: int) -> Path:
    return Path(tempfile.gettempdir()) / f'photogram-ros-domain-{domain}.lock'


def _try_take(domain: int) -> bool:
    try:
        fd = os.open(_lock_path(domain), os.O_RDONLY | os.O_CREAT, 0o666)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        return False
    _held.append(fd)
    return True


def domains_in_use(udp_tables=('/proc/net/udp', '/proc/net/udp6')) -> set[int]:
    """Domain ids 0..232 with a UDP port of their block bound on this machine's network, by any process
    of any user or container that shares it: a DDS participant is on the domain, or a session reserved it.
    `udp_tables` are Linux's socket tables (hexadecimal `address:port` in the second column); an unreadable
    table counts nothing, so elsewhere than on Linux only the lock files keep sessions apart."""
    used = set()
    for table in udp_tables:
        try:
            lines = Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            fields = line.split()
            try:
                port = int(fields[1].rsplit(':', 1)[1], 16)
            except (IndexError, ValueError):
                continue
            d = (port - PORT_BASE) // PORTS_PER_DOMAIN
            if port >= PORT_BASE and d <= DOMAIN_MAX:
                used.add(d)
    return used


def _reserve(domain: int) -> bool:
    """Bind the last UDP port of `domain`'s block for the life of the process (False: already bound)."""
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        s.bind(('0.0.0.0', PORT_BASE + PORTS_PER_DOMAIN * domain + _RESERVE_OFFSET))
    except OSError:
        s.close()
        return False
    _held.append(s)
    return True


def reserve_test_domain(domains: Sequence[int] = TEST_DOMAINS) -> int:
    """A domain id for a test session: one of `domains` with no UDP port of its block bound on this
    machine's network, reserved by binding its last port until the process ends (the session's nodes
    and child processes join it through ROS_DOMAIN_ID). ConfigError when every one is in use."""
    busy = domains_in_use()
    order = list(domains)
    random.shuffle(order)
    for d in order:
        if d not in busy and _reserve(d):
            return d
    raise ConfigError(f'every domain id {min(order)}..{max(order)} has a DDS participant on this machine: set '
                      'ROS_DOMAIN_ID to one of your own for the tests')


def own_domain(avoid: int | None = None) -> int:
    """A domain id in 215..232 that no other photogram_ros process on this machine holds, with no UDP port
    of its block bound by anyone on this machine's network (`domains_in_use`), and not `avoid`, the
    user's own; it is held until the process ends. ConfigError when all are taken."""
    busy = domains_in_use()
    start = os.getpid() % len(OWN_DOMAINS)
    for k in range(len(OWN_DOMAINS)):
        d = OWN_DOMAINS[(start + k) % len(OWN_DOMAINS)]
        if d != avoid and d not in busy and _try_take(d):
            return d
    raise ConfigError(f'every domain id {OWN_DOMAINS.start}..{DOMAIN_MAX} is held by another replay or has a DDS '
                      'participant on this machine: wait for one to end, or share a domain with --domain N')


def shared_domain(domain: int) -> int:
    """`replay --domain N`: hold N as `own_domain` holds its domain, so that two replays never play on
    one domain (each one's tracker would take the other's frames and fixes). A ConfigError when
    another replay on this machine holds N."""
    if not _try_take(domain):
        raise ConfigError(f'--domain {domain}: another replay on this machine plays on ROS_DOMAIN_ID {domain}; '
                          'two replays on one domain mix their flights: choose another --domain, or leave it '
                          'out (a free domain of its own)')
    return domain


def use_domain(domain: int) -> None:
    """Join `domain` from now on (rclpy.init reads ROS_DOMAIN_ID; child processes inherit it)."""
    os.environ['ROS_DOMAIN_ID'] = str(int(domain))
