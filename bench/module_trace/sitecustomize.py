"""Imported by every Python process started with bench/module_trace on PYTHONPATH: when PHOTOGRAM_MODULE_TRACE_DIR
is set, the process writes the photogram_ros files it ran there (photogram_module_trace.py says how); then the
next sitecustomize.py on sys.path runs, as it would have without this one."""

try:
    import photogram_module_trace as _trace
    _trace.install_from_env()
    _trace.chain_next_sitecustomize(__file__)
except Exception as _exc:     # a trace must never stop the process it watches
    import sys
    print(f'module trace: WARN: not installed ({_exc!r})', file=sys.stderr)
