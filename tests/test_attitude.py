"""Body attitude history and the gimbal lever arm: against the simulator's own antenna and known rotations."""
from __future__ import annotations

import numpy as np

from photogram_ros.core.attitude import AttitudeHistory, antenna_offset_enu
from photogram_ros.core.rotations import (angle_between_R, enu_R_flu_from_ned_R_frd, ned_R_frd_from_euler,
                                          quat_from_R, rot_z)


def test_antenna_offset_is_the_simulators_antenna():
    # The simulator places the antenna at pos + ENU_R_NED @ ned_R_frd @ lever_frd (sim/scenario.py);
    # from the REP-103 attitude that mavlink_node publishes the offset must be the same vector.
    from helpers.sim_world import world
    cfg, flight, _, _, _ = world('tiny')
    lever = np.asarray(cfg.lever_arm_frd_m, float)
    for t in (3.0, 11.0, flight.duration_s / 2):
        st = flight.state(t)
        enu_R_flu = enu_R_flu_from_ned_R_frd(ned_R_frd_from_euler(st.roll_rad, st.pitch_rad, st.yaw_rad))
        np.testing.assert_allclose(antenna_offset_enu(enu_R_flu, lever), flight.body_R(st) @ lever, atol=1e-12)
    # Flying forward nose down, the 20 cm mast leans the antenna forward: the camera-frame lever arm of a
    # gimballed camera misses it by centimetres.
    st = flight.state(3.0)
    assert st.pitch_rad < -np.radians(1)            # -5 deg at 5 m/s, plus 2 deg of gusts
    fwd = st.vel_enu / np.linalg.norm(st.vel_enu)
    along = float(fwd @ flight.body_R(st) @ np.array([0.0, 0.0, -0.20]))
    assert along > 0.005


def test_history_interpolates_between_samples_and_knows_its_gaps():
    h = AttitudeHistory(max_age_ns=10_000_000_000, max_gap_ns=200_000_000)
    rate = np.radians(10.0)          # 10 deg/s about up
    for k in range(0, 50):           # 10 Hz for 5 s
        h.add(k * 100_000_000, quat_from_R(rot_z(rate * k * 0.1)))
    R = h.at(1_250_000_000)          # between two samples
    assert angle_between_R(R, rot_z(rate * 1.25)) < 1e-9
    assert angle_between_R(h.at(2_000_000_000), rot_z(rate * 2.0)) < 1e-12
    assert h.at(-30_000_000) is None and h.at(4_930_000_000) is None     # before the first, after the last
    # ... but the end samples hold for 20 ms (clock mapping jitter around an exposure's stamp).
    assert angle_between_R(h.at(4_910_000_000), rot_z(rate * 4.9)) < 1e-12 and h.newest_ns == 4_900_000_000
    # An outage: nothing within max_gap on one side.
    h.add(6_000_000_000, quat_from_R(rot_z(0.0)))
    assert h.at(5_500_000_000) is None
    # Old samples go: 10 s behind the newest.
    h.add(14_500_000_000, quat_from_R(rot_z(0.0)))
    assert h.at(1_250_000_000) is None and len(h) == 7      # 4.5-4.9 s, 6 s and 14.5 s
    # Bad quaternions are ignored; a sample with an existing stamp replaces it.
    h.add(7_000_000_000, [0.0, 0.0, 0.0, 0.0])
    h.add(6_000_000_000, quat_from_R(rot_z(0.5)))
    assert len(h) == 7 and angle_between_R(h.at(6_000_000_000), rot_z(0.5)) < 1e-12
