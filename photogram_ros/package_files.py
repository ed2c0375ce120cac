"""Files installed with the package, found from the package, never from the current directory.

The parameter files of config/ are installed as data files into `<prefix>/share/photogram_ros/config`
by `pip install` (the environment's prefix), `pip install --user` (the user base) and colcon (the
workspace's install/ folder); a source checkout has them in its config/ folder.
"""

from __future__ import annotations

import sys
import sysconfig
from pathlib import Path

PACKAGE = Path(__file__).resolve().parent
SHARE = ('share', 'photogram_ros')


def _prefixes() -> list[Path]:
    """Where the package's data files can be: the source checkout, then the install prefixes."""
    out = [PACKAGE.parent]                                 # a checkout: <repo>/config
    # site-packages is <prefix>/lib/pythonX.Y/site-packages (or <prefix>/local/lib/...): the prefix it was installed in
    out += [PACKAGE.parents[k] for k in (3, 4) if len(PACKAGE.parents) > k]
    out += [Path(p) for p in (sys.prefix, sysconfig.get_config_var('userbase') or '') if p]
    try:
        import site
        out.append(Path(site.getuserbase()))
    except (ImportError, AttributeError):
        pass
    return out


def config_dir() -> Path | None:
    """The folder of the installed parameter files (config/*.yaml), or None when none is found."""
    for prefix in _prefixes():
        for d in (prefix / 'config', prefix.joinpath(*SHARE, 'config')):
            if (d / 'replay.yaml').is_file():
                return d
    return None


def config_file(name: str) -> Path | None:
    """An installed parameter file by name (e.g. 'replay.yaml'), or None."""
    d = config_dir()
    return d / name if d is not None and (d / name).is_file() else None
