"""Dense matching from the final adjustment (io/densify.py) with the stereo and map nodes' settings.

Shared by `replay` (always, unless --live-map) and `export --densify`: the parameter file's
stereo_node and map_node sections give the same stereo, pair choice and fusion as in flight.
"""

from __future__ import annotations

import sys


def densify_with_params(map_dir, out_dir, params_file: str | None, progress: bool = True):
    from photogram_ros.core.fusion import FusionConfig
    from photogram_ros.core.pairs import PairCriteria
    from photogram_ros.io.densify import densify_map
    from photogram_ros.nodes.map_node import MapParams
    from photogram_ros.nodes.stereo_node import StereoNodeParams
    from photogram_ros.params import from_dict, load_params_file

    sections = load_params_file(params_file) if params_file else {}
    sp = from_dict(StereoNodeParams, sections.get('stereo_node', {}), f'{params_file} stereo_node')
    mp = from_dict(MapParams, sections.get('map_node', {}), f'{params_file} map_node')
    criteria = PairCriteria(sp.target_baseline_ratio, sp.min_baseline_ratio, sp.max_baseline_ratio, sp.min_overlap,
                            sp.max_pairs_along, sp.max_pairs_across, sp.max_axis_angle_deg)
    fusion = FusionConfig(mp.cell_m, mp.tile_cells, mp.max_tiles_in_memory, mp.k_sigma, mp.min_tolerance_m,
                          mp.min_confidence)

    def report(done, total):
        if progress and (done == total or done % 25 == 0):
            print(f'\rdense matching from the final adjustment: {done}/{total} keyframes', end='',
                  file=sys.stderr, flush=True)
            if done == total:
                print(file=sys.stderr)

    return densify_map(map_dir, out_dir, sp, criteria, sp.relief_m, fusion, report)
