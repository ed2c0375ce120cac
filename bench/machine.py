"""The machine's figures, printed beside every benchmark result (absolute times mean little here)."""

import os
import platform


def machine_info() -> dict:
    cpu = platform.processor() or ''
    try:
        with open('/proc/cpuinfo') as f:
            for line in f:
                if line.startswith('model name'):
                    cpu = line.split(':', 1)[1].strip()
                    break
    except OSError:
        pass
    import cv2
    import numpy
    return {'cpu': cpu, 'cores': os.cpu_count(), 'python': platform.python_version(), 'numpy': numpy.__version__,
            'opencv': cv2.__version__}
