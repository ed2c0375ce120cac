"""photogram-ros triangulate: offline aerial triangulation of a flight bag or a folder of photos (geotagged, or placed
by their GCPs)."""

from __future__ import annotations

from photogram_ros.commands import common_args

HELP = ('aerial triangulation of a flight bag or of photos (geotagged: EXIF GPS or geo.txt; without positions: placed '
        'by their GCPs), GCPs/check points; report')


def add_arguments(p) -> None:
    p.add_argument('input', help='a flight bag (images + /gps/fix or raw MAVLink), or a folder of geotagged JPEGs '
                                 '(with an optional OpenDroneMap geo.txt)')
    p.add_argument('--gcp', help='the control file: an OpenDroneMap gcp_list.txt (first line a CRS; names CHK* are '
                                 'check points, MTP* manual tie points), or for a bag the targets file `replay --gcp` '
                                 'reads (the same as --targets)')
    p.add_argument('--mtp', help='manual tie points: one row per mark, "px py image name" (points without '
                                 'coordinates marked in several photos where matching fails)')
    p.add_argument('--targets', help='for a bag: the flight\'s control file of ArUco targets, as `replay --gcp` reads '
                                   'it (first line a CRS, then "name marker_id x y z [sigma_h_m sigma_v_m]"; CHK* '
                                   'are check points): the markers found in the keyframes are the observations')
    p.add_argument('--check', default='', help='more check-point names, comma separated')
    p.add_argument('--out', required=True, help='output folder (poses.csv, sparse.ply/.las, report.md/.json)')
    p.add_argument('--camera', help='calibration YAML (ROS camera_calibration layout); default: the bag\'s '
                                    'camera_info, or for photos the simulator truth beside the folder, else the '
                                    'photos\' EXIF (focal length from a DJI XMP, the focal-plane resolution, a '
                                    'sensor table or the 35 mm equivalent; principal point centred, no distortion)')
    p.add_argument('--crs', help='output CRS (default: the GCP CRS, else the UTM zone of the first photo)')
    common_args.add_heights(p)
    p.add_argument('--gcp-sigma', default='0.02,0.02,0.03', help='GCP sigma E,N,U in metres')
    common_args.add_gcp_heights(p, 'a targets file (--targets, or --gcp; a gcp_list.txt says it by its own CRS)',
                                old_policy=True)
    common_args.add_gcp_height_check(p)
    p.add_argument('--neighbours', type=int, default=8, help='photos matched with each photo first (nearest by '
                                                             'position, or largest footprint overlap)')
    p.add_argument('--max-image-px', type=int, default=1000, help='photos: long side of the reduced photo features '
                                                                  'are detected on (px)')
    p.add_argument('--max-features', type=int, default=4000, help='photos: SIFT features per photo')
    p.add_argument('--window', type=int, default=10, help='sliding-window size of the incremental adjustment')
    common_args.add_lever_arm_cam(p, old_flag='--lever-arm')
    p.add_argument('--self-calibrate', default='auto', help='intrinsics refined in the final adjustment, e.g. '
                                                            '"f,k1,k2" (from f, cx, cy, k1, k2, p1, p2, k3), "none", '
                                                            'or "auto" (default: k1,k2 for a camera from the EXIF, '
                                                            'f too with 3+ GCPs, cx,cy too with RTK/PPK-precise '
                                                            'geotags; nothing for a calibration)')
    common_args.add_exif_altitude(p, 'Not given: orthometric, and the report says if the adjusted ground makes that '
                                     'look wrong')
    p.add_argument('--workers', type=int, default=1,
                   help='photos: features, pair matching and the sub-blocks of a split block on a local Dask cluster '
                        'of this many worker processes (default 1: in this process, no Dask)')
    p.add_argument('--scheduler', default=None,
                   help='photos: features, pair matching and sub-blocks on the existing Dask cluster at '
                        'tcp://HOST:PORT (its workers need photogram_ros and the photos and --out at the same path)')
    p.add_argument('--split-photos', type=int, default=None,
                   help='photos: a block of more photos than this is adjusted as overlapping sub-blocks (one Dask '
                        'task each with --workers/--scheduler), merged and checked as one block; 0: never split '
                        '(default: SplitMergeOptions.split_photos, measured in bench/notes_photo_triangulation_scale.md)')
    p.add_argument('--overlap-m', type=float, default=None,
                   help='photos, split-merge: overlap radius between sub-blocks in metres (default: the median '
                        'distance from a photo to its 8th nearest photo)')
    p.add_argument('--quiet', action='store_true', help='no progress lines (on stderr; warnings are still said)')


def _is_bag(path) -> bool:
    """A flight bag: a rosbag2 folder (with its metadata.yaml, or without, as a recording cut short leaves it) or a
    bare .db3 / .mcap / ROS 1 .bag file."""
    from pathlib import Path

    from photogram_ros.nodes.replay_session import source_kind
    p = Path(path)
    return p.exists() and source_kind(p) == 'bag'


def _msl(datum: str | None) -> str | None:
    """The command's datum spelling -> TriangulateOptions' ('orthometric' is its 'msl': EGM2008)."""
    return 'msl' if datum == 'orthometric' else datum


def run(a) -> int:
    import sys

    from photogram_ros.core.control import ControlVettingOptions
    from photogram_ros.core.photo_matching import MatchingOptions
    from photogram_ros.core.split_merge import SplitMergeOptions
    from photogram_ros.io.aerial_triangulation import TriangulateOptions
    from photogram_ros.io.triangulate_action import triangulate
    from photogram_ros.params import floats, from_dict

    cal = a.self_calibrate.strip().lower()
    refine = None if cal == 'auto' else () if cal in ('', 'none') else tuple(
        v.strip() for v in a.self_calibrate.split(',') if v.strip())
    matching = from_dict(MatchingOptions, {'max_image_px': a.max_image_px, 'max_features': a.max_features,
                                           'neighbours': a.neighbours}, 'triangulate')
    split_values = {k: v for k, v in (('split_photos', a.split_photos), ('overlap_m', a.overlap_m))
                    if v is not None}
    split = (None if a.split_photos == 0 else from_dict(SplitMergeOptions, split_values, 'triangulate'))
    opt = TriangulateOptions(
        camera=a.camera, targets=a.targets, gcp=a.gcp, mtp=a.mtp,
        check_names=tuple(s.strip() for s in a.check.split(',') if s.strip()),
        crs=a.crs, gcp_sigma_enu_m=floats(a.gcp_sigma, '--gcp-sigma', 3),
        window=a.window, lever_arm_cam_m=floats(a.lever_arm_cam, '--lever-arm-cam', 3),
        self_calibrate=refine, matching=matching,
        exif_altitude=_msl(a.exif_altitude), takeoff_h_m=a.takeoff_altitude_m,
        takeoff_heights=_msl(a.takeoff_heights), control_heights=a.gcp_heights,
        workers=a.workers, scheduler=a.scheduler, split=split, heights=a.heights,
        vetting=ControlVettingOptions(contradicted_heights='horizontal' if a.gcp_height_check == 'checked' else 'use'))
    from photogram_ros.io.out_dir import usable_folder
    usable_folder(a.out)   # a file or an uncreatable path: said now, not after the adjustment
    log = (lambda text: print(text, file=sys.stderr))
    res = triangulate(a.input, a.out, opt, log=log, progress=not a.quiet, bag=_is_bag(a.input))
    rep = res.report
    ck = rep['check']['rmse']
    rms = rep['reprojection_rms_px']
    print(f"oriented {res.registered}/{res.inputs} images, {res.tie_points} tie points, reprojection "
          + (f'{rms:.3f} px' if rms is not None else 'none') + '; check points: '
          + (f"n={ck['n']} RMSE horizontal {ck['horizontal_m'] * 100:.1f} cm, vertical {ck['vertical_m'] * 100:.1f} cm"
             if ck.get('n') else 'none') + f'; wrote {res.out}')
    faults = (rep.get('control') or {}).get('faults', [])
    if faults:
        print(f'control: {len(faults)} faults found (see the report\'s Control rows)')
    for e in res.damage:
        print(f'bag damaged: {e}')
    v = res.verdict
    print(f"verdict: {v['summary']}" if v else 'verdict: none')
    # Exit status: 4 for a block that failed its own check (the files are written, but wrong); as
    # `replay`'s, 3 for a damaged bag (what it held was triangulated).
    if v and v['status'] == 'failed':
        return 4
    return 3 if res.damage else 0
