"""A frame still compressed (EncodedImage: decoded at the tracker's working size, or whole once), and the keyframe
the tracker hands on (Keyframe: its image read through a property that decodes a compressed one on first read)."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from photogram_ros.core.gnss_fix import GnssFix
from photogram_ros.errors import DataError

# cv2.imdecode flags that decode in grey at 1/n of the size (a JPEG through libjpeg's DCT scaling; other
# formats are decoded whole and resized by OpenCV); EXIF orientation is ignored as in a camera's raw frames.
_REDUCED_GREY = {1: cv2.IMREAD_GRAYSCALE, 2: cv2.IMREAD_REDUCED_GRAYSCALE_2, 4: cv2.IMREAD_REDUCED_GRAYSCALE_4,
                 8: cv2.IMREAD_REDUCED_GRAYSCALE_8}


class EncodedImage:
    """A frame still compressed: `data` the bytes of a JPEG (or PNG, TIFF: what cv2.imdecode reads), as a
    camera or a photo folder gives them (sensor_msgs/CompressedImage's data). The tracker decodes it at
    its working size; `full()` decodes it at full size (BGR), once."""

    def __init__(self, data):
        self.data = np.frombuffer(data, np.uint8) if not isinstance(data, np.ndarray) else data.reshape(-1)
        self._full: np.ndarray | None = None

    def reduced_grey(self, reduce: int) -> np.ndarray:
        """The grey image at 1/`reduce` of the full size (a power of two), pixel i covering full pixels
        [reduce*i, reduce*(i+1)): (ceil(H/reduce), ceil(W/reduce)) uint8. DataError if undecodable."""
        flag = _REDUCED_GREY.get(min(reduce, 8))
        out = cv2.imdecode(self.data, flag | cv2.IMREAD_IGNORE_ORIENTATION) if self.data.size else None
        if out is None:
            raise DataError(f'compressed frame ({self.data.size} bytes) cannot be decoded')
        if reduce > 8:
            h, w = out.shape
            k = reduce // 8
            out = cv2.resize(out, (-(-w // k), -(-h // k)), interpolation=cv2.INTER_AREA)
        return out

    def full(self) -> np.ndarray:
        """The full-size image, BGR uint8 (decoded the first time). DataError if undecodable."""
        if self._full is None:
            img = cv2.imdecode(self.data, cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION) if self.data.size else None
            if img is None:
                raise DataError(f'compressed frame ({self.data.size} bytes) cannot be decoded')
            self._full = img
        return self._full


@dataclass
class Keyframe:
    index: int
    frame_index: int
    stamp_ns: int
    image: np.ndarray          # BGR (read through the property below: a compressed keyframe decodes on first read)
    observations: np.ndarray
    fix: GnssFix | None = None
    overlap: float = float('nan')
    break_before: bool = False
    bridged: bool = False
    # The full image's (width, height): known before an EncodedImage is decoded.
    size: tuple = (0, 0)


def _keyframe_image(self) -> np.ndarray:
    img = self.__dict__['image']
    if isinstance(img, EncodedImage):
        img = img.full()
        if (img.shape[1], img.shape[0]) != tuple(self.size):
            raise DataError(f'keyframe {self.index}: the photo decodes to {img.shape[1]}x{img.shape[0]}, its '
                            f'reduced decode said {self.size[0]}x{self.size[1]}')
        self.__dict__['image'] = img
    return img


def _keyframe_encoded(self) -> EncodedImage | None:
    """The compressed image the keyframe still holds (a frame that came compressed, not decoded at full size
    yet), or None."""
    img = self.__dict__['image']
    return img if isinstance(img, EncodedImage) else None


def _set_keyframe_image(self, value) -> None:
    self.__dict__['image'] = value


# The dataclass keeps `image` as its field; reading it decodes a compressed keyframe once.
Keyframe.image = property(_keyframe_image, _set_keyframe_image)
Keyframe.encoded = _keyframe_encoded
