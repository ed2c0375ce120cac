"""Command-line options that mean the same in every command that takes them, defined once here.

- ``--processes {1,2}``, ``--child-nodes`` in the live graph (`replay`, `run`): bundle, stereo and map in a second
  process by default (one Python process uses about one core).
- ``--gcp FILE``, ``--check NAMES`` in the live graph (`replay`, `run`): the flight's control file, read before
  any node starts into one object (io/control_file.ControlInput) that the graph hands to the bundle node's stage.
- ``--gcp-heights {auto,ellipsoidal,orthometric}``: the vertical datum of the heights in the control file
  (auto: EGM2008 orthometric only when its CRS is compound with EGM2008 heights, e.g. EPSG:32632+3855; else
  ellipsoidal). Never a policy: whether a contradicted GCP height is used is ``--gcp-height-check``.
- ``--gcp-height-check {checked,use}``: checked, a GCP height the GNSS-only block contradicts far beyond both
  sigmas is reported and the GCP used horizontally only; use, every height as given.
- ``--heights {ellipsoidal,orthometric}``: the heights of the products written (WGS84 ellipsoid, or EGM2008).
- ``--exif-altitude {ellipsoidal,orthometric,relative}``, ``--takeoff-altitude-m``, ``--takeoff-heights``: how the
  photos' EXIF GPSAltitude is read (io/image_source.exif_altitude_reading), in `triangulate` and in the live graph
  (`replay`: camera_node's exif_altitude, takeoff_altitude_m, takeoff_heights).
- Height datum values are ``ellipsoidal`` (WGS84) and ``orthometric`` (EGM2008) everywhere; ``msl`` is read as
  ``orthometric``.
- ``--lever-arm-cam X,Y,Z``: the GNSS antenna from the camera in the camera frame (x right, y down, z along
  the optical axis), m. ``--lever-arm`` is reserved for the body frame (forward, right, down), as `geotag`
  takes it.

Old spellings still parse, with a warning on stderr naming the new one (`deprecated`): replay's
``--orthometric``, triangulate's ``--gcp-heights checked|use`` and ``--lever-arm`` (camera frame), and ``msl``.
"""

from __future__ import annotations

import argparse
import sys

GCP_HEIGHTS = ('auto', 'ellipsoidal', 'orthometric')
GCP_HEIGHT_CHECK = ('checked', 'use')
HEIGHTS = ('ellipsoidal', 'orthometric')
LEVER_ARM_CAM_HELP = ('the GNSS antenna from the camera in the camera frame, x right, y down, z along the optical '
                      'axis, m: "x,y,z"')


def deprecated(old: str, new: str) -> None:
    """Say on stderr that an old spelling was used and what replaces it (the command goes on with it)."""
    print(f'warning: {old} is deprecated: use {new} (same meaning)', file=sys.stderr, flush=True)


def height_datum(value: str, flag: str) -> str:
    """A height datum as given -> 'ellipsoidal' or 'orthometric' ('msl' read as 'orthometric', with a warning)."""
    v = value.strip().lower()
    if v == 'msl':
        deprecated(f'{flag} msl', f'{flag} orthometric')
        return 'orthometric'
    return v


class Datum(argparse.Action):
    """A height-datum option whose choices include 'orthometric': 'msl' is taken for it, with a warning."""

    def __call__(self, parser, namespace, value, option_string=None):
        setattr(namespace, self.dest, height_datum(value, option_string))


def datum_choices(*others: str) -> tuple:
    """The choices of a height-datum option: HEIGHTS, then `others` (e.g. 'relative'), then the old 'msl'."""
    return HEIGHTS + others + ('msl',)


def datum_metavar(*others: str) -> str:
    return '{' + ','.join(HEIGHTS + others) + '}'


class _GcpHeights(argparse.Action):
    """--gcp-heights: the datum; the policy values of old triangulate (checked, use) go to --gcp-height-check."""

    def __call__(self, parser, namespace, value, option_string=None):
        if value in GCP_HEIGHT_CHECK:
            deprecated(f'{option_string} {value}', f'--gcp-height-check {value}')
            setattr(namespace, 'gcp_height_check', value)
            return
        setattr(namespace, self.dest, value)


class _Alias(argparse.Action):
    """An old flag that sets a new option's value (`const`), with a warning."""

    def __init__(self, option_strings, dest, new_flag: str, **kwargs):
        self.new_flag = new_flag
        super().__init__(option_strings, dest, **kwargs)

    def __call__(self, parser, namespace, value, option_string=None):
        deprecated(option_string, self.new_flag if self.nargs == 0 else f'{self.new_flag} {value}')
        setattr(namespace, self.dest, self.const if self.nargs == 0 else value)


def add_gcp_heights(p, what: str = 'the control file', old_policy: bool = False) -> None:
    """--gcp-heights (datum); `old_policy`: also take checked|use as the deprecated spelling of --gcp-height-check."""
    choices = GCP_HEIGHTS + (GCP_HEIGHT_CHECK if old_policy else ())
    p.add_argument('--gcp-heights', default='auto', choices=choices, action=_GcpHeights,
                   metavar='{' + ','.join(GCP_HEIGHTS) + '}',
                   help=f'vertical datum of the heights of {what} (auto: EGM2008 orthometric only for a compound '
                        'CRS, e.g. EPSG:32632+3855; else ellipsoidal)')


def add_gcp_height_check(p) -> None:
    p.add_argument('--gcp-height-check', default='checked', choices=GCP_HEIGHT_CHECK,
                   help='checked (default): a GCP height the GNSS-only block contradicts far beyond both sigmas '
                        '(placeholders such as 0 or 400 m) is reported and the GCP used horizontally only; use: '
                        'every height as given (the block bends to fit it)')


def add_live_control(p) -> None:
    """--gcp, --check and --gcp-heights of the live graph (replay, run): the flight's control file (read by
    live_control)."""
    p.add_argument('--gcp', default='', help='control-point file of the flight\'s ArUco targets (first line a CRS, '
                                         'then "name marker_id x y z [sigma_h_m sigma_v_m]"): GCPs constrain the '
                                         'adjustment, CHK* names are check points; the simulator writes targets.txt')
    p.add_argument('--check', default='', help='more check-point names of the --gcp file, comma separated')
    add_gcp_heights(p, 'the --gcp file')


def live_control(a):
    """The flight's control (io/control_file.ControlInput) read now from --gcp, --check, --gcp-heights, so that a
    bad file is said before any node starts; the command hands it to the graph (the bundle node's adjustment
    stage) and to the report. None without --gcp (a note when --check is given alone)."""
    from photogram_ros.io.control_file import ControlInput
    if not a.gcp:
        if a.check:
            print('note: --check without --gcp has no effect (without a control file every target is a check point)')
        return None
    return ControlInput.read(a.gcp, a.check.split(','), a.gcp_heights)


CHILD_ROLES = ('bundle', 'stereo', 'map')


def add_processes(p) -> None:
    """--processes and --child-nodes of the live graph (replay, run): read back by child_roles."""
    p.add_argument('--processes', type=int, choices=(1, 2), default=2,
                   help='2 (default): the --child-nodes run in a second process, on a second core (one Python '
                        'process uses about one core); 1: every node in one process')
    p.add_argument('--child-nodes', default=','.join(CHILD_ROLES),
                   help='nodes of the second process with --processes 2 (among ' + ', '.join(CHILD_ROLES) + ')')


def child_roles(a, roles=CHILD_ROLES) -> tuple:
    """The roles of the second process (those of `roles` that --child-nodes names; none with --processes 1); a
    ConfigError for a role that cannot go there (the camera, the tracker and the MAVLink decoder take the
    flight's input and stay in the main process)."""
    from photogram_ros.errors import ConfigError
    child = tuple(r.strip() for r in a.child_nodes.split(',') if r.strip()) if a.processes == 2 else ()
    if set(child) - set(CHILD_ROLES):
        raise ConfigError(f'--child-nodes {a.child_nodes!r}: choose among {", ".join(CHILD_ROLES)}')
    return tuple(r for r in child if r in roles)


def add_heights(p, old_flag: str | None = None) -> None:
    """--heights of the products; `old_flag` (e.g. '--orthometric'): a deprecated switch for `--heights orthometric`."""
    p.add_argument('--heights', default='ellipsoidal', choices=HEIGHTS,
                   help='heights of the products: WGS84 ellipsoidal (default) or orthometric above the EGM2008 geoid')
    if old_flag:
        p.add_argument(old_flag, dest='heights', nargs=0, const='orthometric', action=_Alias,
                       new_flag='--heights orthometric', help=argparse.SUPPRESS)


def add_exif_altitude(p, not_given: str = 'Not given: orthometric') -> None:
    """--exif-altitude, --takeoff-altitude-m and --takeoff-heights: how the photos' EXIF GPSAltitude is read (one rule
    for triangulate and camera_node: io/image_source.exif_altitude_reading); `not_given`: what the command does
    without --exif-altitude."""
    p.add_argument('--exif-altitude', choices=datum_choices('relative'), action=Datum,
                   metavar=datum_metavar('relative'), default=None,
                   help='what the photos\' EXIF GPSAltitude is: orthometric (EGM2008; "above mean sea level", the '
                        'EXIF standard; default; a DJI XMP AbsoluteAltitude where the EXIF has none), ellipsoidal '
                        '(WGS84), or relative to the take-off point (many drones; needs --takeoff-altitude-m). '
                        + not_given)
    p.add_argument('--takeoff-altitude-m', type=float, default=None,
                   help='height of the take-off point (m), for --exif-altitude relative')
    p.add_argument('--takeoff-heights', choices=datum_choices(), action=Datum, metavar=datum_metavar(),
                   default='orthometric',
                   help='vertical datum of --takeoff-altitude-m: orthometric (EGM2008; default) or ellipsoidal (WGS84)')


def exif_altitude_overrides(a) -> dict:
    """camera_node's parameters of --exif-altitude, --takeoff-altitude-m, --takeoff-heights (those given); with
    --exif-altitude checked now as camera_node would check them (io/image_source.exif_altitude_reading; a take-off
    height alone goes with the parameter file's exif_altitude, which camera_node checks)."""
    from photogram_ros.io.image_source import exif_altitude_reading
    if a.exif_altitude:
        exif_altitude_reading(a.exif_altitude, a.takeoff_altitude_m, a.takeoff_heights)
    out = {}
    if a.exif_altitude:
        out['exif_altitude'] = a.exif_altitude
    if a.takeoff_altitude_m is not None:
        out['takeoff_altitude_m'] = float(a.takeoff_altitude_m)
        out['takeoff_heights'] = a.takeoff_heights
    return out


def add_lever_arm_body(p, extra_help: str = '') -> None:
    """--lever-arm: the GNSS antenna from the camera in the body frame (forward, right, down), m, as `geotag` and the
    bundle node's lever_arm_body_frd_m take it; `extra_help`: what the command adds (e.g. how it is turned)."""
    p.add_argument('--lever-arm', default='0,0,0',
                   help='the GNSS antenna from the camera in the body frame, forward,right,down, m: "x,y,z"'
                        + (f'. {extra_help}' if extra_help else '') + ' (default: 0,0,0)')


def add_lever_arm_cam(p, old_flag: str | None = None) -> None:
    """--lever-arm-cam; `old_flag` (e.g. '--lever-arm'): its deprecated spelling, same value."""
    p.add_argument('--lever-arm-cam', default='0,0,0', help=LEVER_ARM_CAM_HELP + ' (default: 0,0,0)')
    if old_flag:
        p.add_argument(old_flag, dest='lever_arm_cam', action=_Alias, new_flag='--lever-arm-cam',
                       help=argparse.SUPPRESS)
