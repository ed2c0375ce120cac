"""photogram-ros calibrate: chessboard calibration of the camera, written as a calibration YAML."""

from __future__ import annotations

HELP = 'calibrate the camera from chessboard photos and write a calibration YAML'


def add_arguments(p) -> None:
    p.add_argument('images', nargs='+', help='chessboard photos (the whole board visible in each)')
    p.add_argument('--board', default='9x6', help='inner corners COLSxROWS (default 9x6)')
    p.add_argument('--square', type=float, default=1.0, help='square size (any unit, default 1.0)')
    p.add_argument('--out', default='calibration.yaml', help='output YAML (default calibration.yaml)')
    p.add_argument('--format', choices=('ros', 'opencv'), default='ros',
                   help='ros: camera_calibration YAML (default); opencv: cv::FileStorage YAML')
    p.add_argument('--camera-name', default='camera', help='camera_name written in the ROS YAML')
    p.add_argument('--min-views', type=int, default=5, help='fewest usable views accepted (default 5)')


def run(a) -> int:
    import cv2
    import yaml

    from photogram_ros.core.calibration import calibrate, parse_board
    from photogram_ros.core.camera import save_opencv_yaml
    from photogram_ros.errors import ConfigError, DataError

    if a.min_views < 3:
        raise ConfigError(f'--min-views {a.min_views}: at least 3 views of the board (fewer cannot separate the '
                          'focal length from the board\'s distance)')
    views = []
    for path in a.images:
        img = cv2.imread(path, cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise DataError(f'cannot read the image {path}')
        views.append((path, img))
    res = calibrate(views, parse_board(a.board), a.square, min_views=a.min_views)
    for name, why in res.rejected.items():
        print(f'  rejected {name}: {why}')
    if not res.ok:
        print(f'calibration failed: {res.message}')
        return 1
    for name, e in res.view_rms_px.items():
        print(f'  {name}: {e:.3f} px')
    c = res.camera
    print(f'{res.message}: fx={c.fx:.2f} fy={c.fy:.2f} cx={c.cx:.2f} cy={c.cy:.2f} '
          f'dist={", ".join(f"{v:.5f}" for v in c.dist)}')
    if a.format == 'opencv':
        save_opencv_yaml(c, a.out, {'rms_px': res.rms_px})
    else:
        with open(a.out, 'w') as f:
            yaml.safe_dump(c.to_ros_yaml_dict(a.camera_name), f, sort_keys=False)
    print(f'wrote {a.out}')
    return 0
