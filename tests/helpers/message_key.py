"""A content key for a message, equal for equal messages whatever the CDR padding."""

import hashlib


def message_key(msg) -> str:
    h = hashlib.sha1()
    stamp = getattr(getattr(msg, 'header', None), 'stamp', None)
    if stamp is not None:
        h.update(f'{stamp.sec}.{stamp.nanosec}'.encode())
    for name in ('data', 'latitude', 'longitude', 'altitude'):
        if hasattr(msg, name):
            v = getattr(msg, name)
            h.update(bytes(v) if not isinstance(v, float) else repr(v).encode())
    return h.hexdigest()
