"""bench/ppk_formats.py's geotag_height_lean: the lean of the geotags' height errors across the block (weighted as
their XMP states) and the ground shift it makes at the block's depth, which explains a survey's check points
without GCPs (a block takes its tilt from its fixes' heights)."""

import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'bench'))
import ppk_formats  # noqa: E402


def _survey(tmp_path, lean_e, float_dz_m):
    """Nine photos on three lines 17 m apart at 40 m over check points at 0 m; the fixed photos' heights lean
    `lean_e` (dz/dE), the FLOAT ones (every third, sigma 0.8 m) `float_dz_m` off."""
    truth, per_image = {}, []
    for k in range(9):
        x, y = 17.0 * (k // 3 - 1), 10.0 * (k % 3)
        is_float = k % 3 == 2
        dz = float_dz_m if is_float else lean_e * x
        truth[f'IMG_{k}.JPG'] = {'flag': 34 if is_float else 50,
                                 'sd_neu_m': [0.5, 0.5, 0.8] if is_float else [0.0136, 0.0136, 0.0286],
                                 'error_enu_m': [0.0, 0.0, dz]}
        per_image.append({'image': f'IMG_{k}.JPG', 'position_map_m': [x, y, 40.0]})
    (tmp_path / 'rtk_truth.json').write_text(json.dumps(truth))
    rep = {'per_image': per_image,
           'check': {'points': [{'surveyed_map_m': [0.0, 0.0, 0.0], 'residual_m': [0.04, 0.0, 0.0]},
                                {'surveyed_map_m': [5.0, 5.0, 0.0], 'residual_m': [0.02, 0.01, 0.0]}]}}
    return rep


def test_lean_of_the_fixed_heights_and_its_ground_shift(tmp_path):
    rep = _survey(tmp_path, 0.001, 0.5)
    got = ppk_formats.geotag_height_lean(tmp_path, rep)
    # The FLOAT photos (all at y 20 m, 0.5 m high) weigh (0.0286 / 0.8)^2 of a fixed one: the lean is the fixed
    # photos' 1 mrad east, and northward 0.19 mrad (unweighted they would make it 25 mrad).
    assert abs(got['geotag_height_lean_mrad'][0] - 1.0) < 0.01
    assert 0.0 < got['geotag_height_lean_mrad'][1] < 0.3
    assert got['block_depth_m'] == 40.0
    assert abs(got['lean_ground_shift_m'][0] - 0.04) < 0.001
    assert np.allclose(got['check_mean_enu_m'], [0.03, 0.005, 0.0])


def test_no_truth_no_figures(tmp_path):
    assert ppk_formats.geotag_height_lean(tmp_path, {'check': {'points': [{}]}}) == {}
