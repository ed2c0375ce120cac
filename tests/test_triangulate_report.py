"""The triangulate report: figures (PNG, in the HTML), intrinsics sigma and per-image figures in report.json."""

import json
import re
import subprocess
import sys

import numpy as np

from conftest import ROOT

FIGURES = ('reprojection_hist.png', 'per_image_rms.png', 'gnss_residuals.png', 'plan.png')


def test_triangulate_report_has_figures_and_intrinsics_sigma(sample_bag, tmp_path):
    out = tmp_path / 'at'
    r = subprocess.run([sys.executable, '-m', 'photogram_ros.cli', 'triangulate', str(sample_bag), '--out', str(out),
                        '--lever-arm=0,-0.05,-0.20', '--self-calibrate', 'f,k1'],
                       cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    html = (out / 'report.html').read_text()
    md = (out / 'report.md').read_text()
    for name in FIGURES:
        png = out / name
        assert png.exists() and png.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n', name
        assert f']({name})' in md, name
    # The HTML embeds every figure (one self-contained file).
    assert len(re.findall(r'<img src="data:image/png;base64,', html)) >= len(FIGURES)
    assert 'Self-calibrated intrinsics with sigma' in html
    rep = json.loads((out / 'report.json').read_text())
    assert set(FIGURES) <= set(rep['figure_files'].values())
    sc = rep['self_calibration']
    # Sigma in pixels for f: small (RTK, 40+ photos) but not zero; k1 unitless; s0 about the image noise.
    assert 0.0 < sc['fx']['sigma'] < 5.0 and sc['fy']['sigma'] == sc['fx']['sigma']
    assert 0.0 < sc['k1']['sigma'] < 0.05
    assert 'sigma' not in sc['cx'] and 0.05 < sc['s0_px'] < 3.0
    # Every figure's numbers: histogram counts add up to the observations; per-image statistics.
    h = rep['reprojection_histogram']
    assert sum(h['counts']) == h['n'] == rep['observations'] and len(h['edges_px']) == len(h['counts']) + 1
    pim = rep['per_image']
    assert len(pim) == rep['registered'] >= 40
    assert all(np.isfinite(p['reprojection_rms_px']) and len(p['position_map_m']) == 3 for p in pim)
    assert sum(p['gnss_residual_enu_m'] is not None for p in pim) >= 40
