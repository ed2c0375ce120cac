"""MAVLink ingest node: flight-controller GNSS/RTK fixes, attitude and camera triggers onto ROS topics.

Input: a link named by `url` (udpin:/udpout:/tcp:/tcpin:/serial device/.tlog file), or raw bytes
on `input_topic` (std_msgs/UInt8MultiArray, one or more packets each, as bags carry them).

Output (all RELIABLE, depth 100, which also matches best-effort subscribers; each overridable per topic from the
parameters file, nodes/qos.py):
- /gps/fix (sensor_msgs/NavSatFix): the best receiver's fix, stamped at the fix epoch on the UNIX
  clock, altitude above the WGS84 ellipsoid (REP-145). Status: RTK float/fixed -> GBAS_FIX,
  DGPS/PPP -> SBAS_FIX, 2D/3D/static -> FIX, none -> NO_FIX with NaN position and UNKNOWN covariance.
- /gps/fix_type (std_msgs/UInt8): the full MAVLink GPS_FIX_TYPE (0..8) of each /gps/fix, published
  just before it, so RTK float (5) and RTK fixed (6) stay distinguishable.
- /gps/fix_1, /gps/fix_2: each receiver's own fixes (GPS_RAW_INT, GPS2_RAW).
- /mavlink/attitude (sensor_msgs/Imu): orientation of body FLU in ENU (REP-103) with covariance.
- /camera/trigger (sensor_msgs/NavSatFix): one per exposure, stamped at the exposure time, with the
  camera position (CAMERA_FEEDBACK, or CAMERA_TRIGGER interpolated between fixes) and the accuracy
  of the fix it came from; frame_id 'camera_<index>'.
- /diagnostics: link state, message rates, CRC/parse errors, lost packets, rejected signatures,
  fix type, satellites, RTK baseline, time-sync offset/drift/residual.
"""

from __future__ import annotations

import os
import sys
import threading
import time
from dataclasses import dataclass

from rclpy.node import Node
from sensor_msgs.msg import NavSatFix
from std_msgs.msg import UInt8, UInt8MultiArray

from photogram_ros import msgs
from photogram_ros.core import gnss_fix as gf
from photogram_ros.errors import ConfigError, MavlinkError, PhotogramError
from photogram_ros.io.mavlink_framing import MavlinkStream, read_tlog, signing_key
from photogram_ros.io.mavlink_ingest import Attitude, FixEvent, Ingest, Trigger
from photogram_ros.io.mavlink_link import Link, is_live_url
from photogram_ros.nodes.diagnostics import ERROR, OK, WARN, Diagnostics
from photogram_ros.nodes import qos
from photogram_ros.nodes.node_main import run_node
from photogram_ros.nodes.ros_params import declare
from photogram_ros.params import param

RATE_TYPES = ('HEARTBEAT', 'GPS_RAW_INT', 'GPS2_RAW', 'GPS_RTK', 'GPS2_RTK', 'GLOBAL_POSITION_INT', 'ATTITUDE',
              'ATTITUDE_QUATERNION', 'SYSTEM_TIME', 'TIMESYNC', 'CAMERA_FEEDBACK', 'CAMERA_TRIGGER')


@dataclass
class MavlinkParams:
    url: str = param('', 'MAVLink source: udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT, tcpin:HOST:PORT, '
                         'a serial device (/dev/ttyUSB0, with baud) or a .tlog file; empty = subscribe to '
                         'input_topic (raw bytes, e.g. from a bag)')
    baud: int = param(57600, 'Serial baud rate', min=1200, max=4_000_000)
    input_topic: str = param('mavlink/from_fcu', 'Topic of raw MAVLink bytes (std_msgs/UInt8MultiArray) '
                                                  'used when url is empty')
    tlog_rate: float = param(1.0, 'Replay speed of a .tlog url (1 = recorded timing, 0 = as fast as possible)',
                             min=0.0, max=10000.0)
    sysid: int = param(0, 'Accept only this MAVLink system id (0 = any)', min=0, max=255)
    compid: int = param(0, 'Accept only this component id (0 = any)', min=0, max=255)
    signing_key: str = param('', 'MAVLink 2 signing secret: 64 hex digits, or a passphrase (SHA-256, as '
                                 'MAVProxy); empty = no signature check')
    signing_link_id: int = param(-1, 'Accept signed packets only from this link id (-1 = any)', min=-1, max=255)
    allow_unsigned: bool = param(False, 'With a signing key: also accept unsigned packets')
    clock_source: str = param('auto', 'Autopilot boot time -> stamps: system_time (SYSTEM_TIME UNIX time), '
                                      'arrival (lower envelope of arrival times on the ROS clock), auto (the '
                                      'first when available)', choices=('auto', 'system_time', 'arrival'))
    trigger_source: str = param('auto', 'Camera events from CAMERA_FEEDBACK, CAMERA_TRIGGER, or auto '
                                        '(feedback when the autopilot sends it)',
                                choices=('auto', 'feedback', 'trigger'))
    uere_m: list = param([0.0, 0.0, 5.0, 2.5, 0.7, 0.25, 0.015, 2.5, 0.1],
                         'Error model when h_acc/v_acc are absent: 1-sigma per axis = DOP * uere_m[fix_type], '
                         'one value per MAVLink fix type 0..8, m')
    vdop_over_hdop: float = param(1.5, 'VDOP assumed as this times HDOP when epv is not sent', min=0.1, max=10.0)
    max_fix_age_s: float = param(1.0, 'A receiver whose last fix is older than this cannot be the best one, s',
                                 min=0.05, max=60.0)
    publish_no_fix: bool = param(True, 'Publish NO_FIX NavSatFix messages (NaN position) when a fix is lost')
    frame_id: str = param('gps', 'frame_id of the GNSS antenna')
    attitude_frame_id: str = param('base_link', 'frame_id of the attitude (body FLU)')
    attitude_sigma_rp_rad: float = param(0.0175, '1-sigma of roll and pitch reported in the Imu covariance, rad',
                                         min=0.0, max=3.2)
    attitude_sigma_yaw_rad: float = param(0.05, '1-sigma of yaw reported in the Imu covariance, rad',
                                          min=0.0, max=3.2)
    link_timeout_s: float = param(3.0, 'No packet for this long = link lost (reported), s', min=0.1, max=600.0)
    diagnostics_period_s: float = param(1.0, 'Period of /diagnostics, s', min=0.05, max=60.0)

    def check(self) -> None:
        if len(self.uere_m) != 9 or any(not (isinstance(v, (int, float)) and v >= 0) for v in self.uere_m):
            raise ConfigError('uere_m needs 9 non-negative values, one per MAVLink fix type 0..8')


OUTPUT_DEPTH = 100   # history of the output topics (reliable; overridable per topic: nodes/qos.py)


class MavlinkNode(Node):
    def __init__(self, overrides: dict | None = None, **node_kwargs):
        super().__init__('mavlink_node', **node_kwargs)
        p = self.params = declare(self, MavlinkParams, overrides)
        self.diag = Diagnostics(self, period_s=p.diagnostics_period_s, hardware_id='mavlink')
        key = signing_key(p.signing_key) if p.signing_key else None
        self.stream = MavlinkStream(secret_key=key, allow_unsigned=p.allow_unsigned, link_id=p.signing_link_id,
                                    sysid=p.sysid, compid=p.compid)
        self.ingest = Ingest(clock_source=p.clock_source,
                             error_model=gf.ErrorModel(tuple(float(v) for v in p.uere_m), p.vdop_over_hdop),
                             max_fix_age_s=p.max_fix_age_s, trigger_source=p.trigger_source,
                             on_problem=self.diag.problem)
        self.pub_fix = qos.publisher(self, NavSatFix, 'gps/fix', qos.reliable(OUTPUT_DEPTH))
        self.pub_fix_type = qos.publisher(self, UInt8, 'gps/fix_type', qos.reliable(OUTPUT_DEPTH))
        self.pub_rx: dict = {}
        from sensor_msgs.msg import Imu
        self.pub_att = qos.publisher(self, Imu, 'mavlink/attitude', qos.reliable(OUTPUT_DEPTH))
        self.pub_trigger = qos.publisher(self, NavSatFix, 'camera/trigger', qos.reliable(OUTPUT_DEPTH))
        self._att_var = (p.attitude_sigma_rp_rad ** 2, p.attitude_sigma_rp_rad ** 2, p.attitude_sigma_yaw_rad ** 2)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._last_packet_mono = None
        self._link_up = False
        self._best_fix_type = None
        self._damaged_reported = 0
        # (bytes_in, packets, signature_rejected, unsigned_rejected, fixes + attitudes published) at the last update
        self._seen = (0, 0, 0, 0, 0)
        self.published = {'fix': 0, 'attitude': 0, 'trigger': 0}
        self.input_done = threading.Event()
        self._last_bytes_s = None          # _note_gap: the latest clock reading at raw bytes
        self._longest_silence_s = 0.0
        self._thread = None
        self._diag_timer = self.create_timer(p.diagnostics_period_s, self._update_diagnostics)
        if p.url:
            target = self._run_tlog if not is_live_url(p.url) else self._run_link
            if not is_live_url(p.url) and not os.path.isfile(p.url):
                raise ConfigError(f'url {p.url!r} is neither a link (udpin:, udpout:, tcp:, tcpin:, /dev/...) '
                                  'nor an existing .tlog file')
            self._thread = threading.Thread(target=target, name='mavlink_input', daemon=True)
            self._thread.start()
        else:
            self.messages_in = 0
            qos.subscription(self, UInt8MultiArray, p.input_topic, self._on_bytes, qos.reliable(1000))

    # --- inputs ------------------------------------------------------------------------------------

    def _now_s(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    def _on_bytes(self, msg: UInt8MultiArray) -> None:
        if self._stop.is_set():   # stop_input(): the flight is being stopped
            return
        now_s = self._now_s()
        self._note_gap(now_s)
        self.feed(msgs.bytes_from_msg(msg), now_s)
        self.messages_in += 1   # lets a bag replay wait until every recorded packet is decoded

    def _note_gap(self, now_s: float) -> None:
        """Raw bytes (a bag, or a bridge) on the node's clock, the flight's in a replay: a silence of the
        autopilot longer than link_timeout_s, or the clock going back, is a WARN naming when and how long
        (the wall-clock link check cannot see a silence recorded in a bag)."""
        last = self._last_bytes_s
        if now_s <= 0.0:    # no clock yet (use_sim_time before the first /clock)
            return
        self._last_bytes_s = now_s if last is None else max(last, now_s)
        if last is None:
            return
        gap = now_s - last
        if gap > self.params.link_timeout_s:
            self.diag.count('link_silences')
            self._longest_silence_s = max(self._longest_silence_s, gap)
            self.diag.set('link_longest_silence_s', round(self._longest_silence_s, 1))
            self.diag.problem(f'the autopilot was silent for {gap:.1f} s (clock {last:.1f} -> {now_s:.1f} s, more '
                              f'than link_timeout_s {self.params.link_timeout_s:g}): no fix, attitude or camera '
                              'event in that time', WARN)
        elif gap < -1.0:
            self._last_bytes_s = now_s   # the new time line from here: said once
            self.diag.count('link_clock_back')
            self.diag.problem(f'the clock went back {-gap:.1f} s between two MAVLink messages ({last:.1f} -> '
                              f'{now_s:.1f} s): a bag played twice or a stamp jump', WARN)

    def feed(self, data: bytes, arrival_s: float | None, final: bool = False) -> None:
        """Raw bytes from any transport -> decoded messages -> published topics."""
        with self._lock:
            try:
                decoded = self.stream.feed(data, final=final)
            except Exception as exc:     # a framing bug must not take the node down
                self.diag.problem(f'MAVLink framing failed: {exc!r}', ERROR)
                return
            for m in decoded:
                self._handle(m, arrival_s)

    def _handle(self, m, arrival_s) -> None:
        self._last_packet_mono = time.monotonic()
        mtype = m.get_type()
        if mtype in RATE_TYPES:
            self.diag.count(f'rx_{mtype}')
        try:
            for ev in self.ingest.handle(m, arrival_s):
                self._publish(ev)
        except PhotogramError as exc:
            self.diag.problem(f'{mtype}: {exc}')
        except Exception as exc:          # one bad message never stops the node
            self.diag.problem(f'{mtype} could not be handled: {exc!r}', ERROR)

    def _run_link(self) -> None:
        p = self.params
        link = None
        while not self._stop.is_set():
            try:
                if link is None:
                    link = Link(p.url, p.baud)
                    self.get_logger().info(f'listening on {p.url}')
                data = link.read(0.2)
                if data:
                    self.feed(data, time.time())
            except (MavlinkError, OSError, Exception) as exc:    # a link that drops comes back
                self.diag.problem(f'link {p.url}: {exc}; reopening', ERROR)
                if link is not None:
                    link.close()
                link = None
                self._stop.wait(1.0)
        if link is not None:
            link.close()

    def _run_tlog(self) -> None:
        p = self.params
        try:
            stream = MavlinkStream(secret_key=self.stream.mav.signing.secret_key, allow_unsigned=p.allow_unsigned,
                                   link_id=p.signing_link_id, sysid=p.sysid, compid=p.compid, record_gap=8)
            messages, _ = read_tlog(p.url, stream)
            with self._lock:
                self.stream = stream
        except PhotogramError as exc:
            self.diag.problem(str(exc), ERROR)
            self.input_done.set()
            return
        wall0, t0 = time.monotonic(), None
        for m, t_rec in messages:
            if self._stop.is_set():
                break
            if p.tlog_rate > 0 and t_rec is not None:
                t0 = t_rec if t0 is None else t0
                delay = wall0 + (t_rec - t0) / p.tlog_rate - time.monotonic()
                if delay > 0:
                    self._stop.wait(delay)
            with self._lock:
                self._handle(m, t_rec)
        self.ingest.flush()
        self.get_logger().info(f'end of {p.url}: {self.published}')
        self.input_done.set()

    # --- outputs -----------------------------------------------------------------------------------

    def _rx_pub(self, receiver: int):
        if receiver not in self.pub_rx:
            self.pub_rx[receiver] = qos.publisher(self, NavSatFix, f'gps/fix_{receiver + 1}',
                                                  qos.reliable(OUTPUT_DEPTH))
        return self.pub_rx[receiver]

    def _fix_msg(self, fix: gf.GnssFix) -> NavSatFix:
        return msgs.navsatfix_from_gnss_fix(fix, self.params.frame_id)

    def _publish(self, ev) -> None:
        if isinstance(ev, FixEvent):
            fix = ev.fix
            self.diag.count(f'fix_{gf.fix_name(fix.fix_type)}')
            if not fix.has_position and not self.params.publish_no_fix:
                return
            msg = self._fix_msg(fix)
            if ev.per_receiver:
                self._rx_pub(fix.receiver).publish(msg)
            if ev.best:
                if self._best_fix_type is not None and fix.fix_type != self._best_fix_type:
                    # Mode changes (RTK fixed -> float, outages) are what users need to see afterwards.
                    self.diag.problem(f'GNSS fix {gf.fix_name(self._best_fix_type)} -> {gf.fix_name(fix.fix_type)}',
                                      WARN if fix.fix_type < self._best_fix_type else OK)
                self._best_fix_type = fix.fix_type
                self.pub_fix_type.publish(UInt8(data=int(fix.fix_type) & 0xFF))
                self.pub_fix.publish(msg)
                self.published['fix'] += 1
        elif isinstance(ev, Attitude):
            self.pub_att.publish(msgs.imu_orientation_msg(int(round(ev.t_s * 1e9)), ev.q_enu_flu_xyzw, self._att_var,
                                                          ev.rates_flu_rad_s, 0.01 ** 2,
                                                          self.params.attitude_frame_id))
            self.published['attitude'] += 1
        elif isinstance(ev, Trigger):
            self.pub_trigger.publish(msgs.navsatfix_from_gnss_fix(ev.fix, f'camera_{ev.seq}'))
            self.published['trigger'] += 1

    def _update_diagnostics(self) -> None:
        d = self.diag
        with self._lock:
            st = self.stream.stats
            for k in ('bytes_in', 'packets', 'crc_errors', 'junk_bytes', 'unknown_msgid', 'signature_rejected',
                      'unsigned_rejected', 'filtered', 'seq_lost'):
                d.set(f'link_{k}', getattr(st, k))
            for k, v in self.ingest.diagnostics().items():
                d.set(k, v)
            for k, v in self.ingest.counts.items():
                if k.islower():
                    d.set(k, v)
        for what in self._nothing_usable(st):
            d.problem(what, WARN)
        damaged = st.crc_errors + st.junk_bytes
        if damaged > self._damaged_reported:
            d.problem(f'corrupted MAVLink data: {st.crc_errors} CRC errors, {st.junk_bytes} junk bytes so far', WARN)
            self._damaged_reported = damaged
        for t in RATE_TYPES:
            r = d.rate_hz(f'rx_{t}')
            if r > 0:
                d.set(f'rate_{t}_hz', round(r, 2))
        for k, v in self.published.items():
            d.set(f'published_{k}', v)
        quiet = self._last_packet_mono is None or time.monotonic() - self._last_packet_mono > self.params.link_timeout_s
        if self.input_done.is_set():
            d.set('link_state', 'end of log')
            return
        if self._stop.is_set():
            d.set('link_state', 'stopped: the end of flight takes no more input')
            return
        if quiet and self._link_up:
            d.problem(f'MAVLink link lost: no packet for {self.params.link_timeout_s:g} s', WARN)
        elif not quiet and not self._link_up and self._last_packet_mono is not None:
            self.get_logger().info('MAVLink link up')
        self._link_up = not quiet
        d.set('link_state', 'up' if self._link_up else 'down')
        if st.signature_rejected or st.unsigned_rejected:
            d.set('signing', f'{st.signature_rejected} bad signatures, {st.unsigned_rejected} unsigned rejected')

    def _nothing_usable(self, st) -> list[str]:
        """WARN reasons when bytes or packets arrived since the last update but none could be used: every
        packet rejected by the signature check (a wrong signing_key, or an autopilot that does not sign),
        or bytes that hold no MAVLink packet at all (a wrong baud rate, another protocol)."""
        used = self.published['fix'] + self.published['attitude']
        now = (st.bytes_in, st.packets, st.signature_rejected, st.unsigned_rejected, used)
        bytes_new, packets_new, bad_sig, unsigned, used_new = (a - b for a, b in zip(now, self._seen))
        self._seen = now
        if not bytes_new or used_new:
            return []
        if bad_sig or unsigned:   # the packets that passed (a radio's, another component's) gave no fix
            what = 'every packet is rejected' if not packets_new else 'no fix or attitude passes'
            out = []
            if bad_sig:
                out.append(f'no usable MAVLink: {what}: {st.signature_rejected} with a wrong signature so far '
                           '(signing_key differs from the autopilot\'s?); no GNSS fix, no attitude')
            if unsigned:
                out.append(f'no usable MAVLink: {what}: {st.unsigned_rejected} unsigned so far (the autopilot does '
                           'not sign: enable signing on it, or set allow_unsigned); no GNSS fix')
            return out
        if packets_new:
            return []
        if st.packets == 0 and bytes_new > 280:   # more than the longest packet: not one cut by the period
            return [f'no usable MAVLink: {st.bytes_in} bytes received and no packet decodes (a wrong baud rate, '
                    'or not MAVLink?); no GNSS fix, no attitude']
        return []

    def stop_input(self) -> None:
        """The flight is being stopped: read and publish no more (the link's thread ends within 0.2 s;
        bytes on input_topic are ignored), so the end of flight works on what came before."""
        self._stop.set()
        self.diag.set('link_state', 'stopped: the end of flight takes no more input')

    def destroy_node(self):
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        return super().destroy_node()


def main(argv=None) -> int:
    """Console script `mavlink_node`."""
    return run_node(MavlinkNode, argv)


if __name__ == '__main__':
    sys.exit(main())

