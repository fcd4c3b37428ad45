"""Raw-equivalent load: what streaming the raw stereo images would need (thesis 8.4).

The thesis contrasts the bandwidth of sharing aggregated submaps (58 KB/s: 700 KB
submaps at 0.04 Hz) with that of the raw stereo streams, which it gives as
"38.75 MB/s at 14.3 Hz and 1.25 MB image size". The formula here is

    bytes/s = sum over robots of  pairs x cameras_per_pair x width x height
                                  x channels x bytes_per_channel x rate_hz

For the LRU's Guppy PRO F-125B (1292 x 964 px, greyscale, thesis 7.1) an image is
1 245 488 B, the thesis's 1.25 MB; one stereo pair at 14.3 Hz then streams
35.62 MB/s (35.75 MB/s with exactly 1.25 MB images). The thesis's 38.75 MB/s is
31 images/s of 1.25 MB, i.e. a pair at 15.5 Hz: its three figures do not agree with
each other, so no formula reproduces all three; this one reproduces the image size
and is exact for the rate it is given.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

from comms.errors import CommsError


@dataclass(frozen=True, slots=True)
class StereoStream:
    """One robot's stereo cameras: ``pairs`` pairs of ``cameras_per_pair`` cameras
    each, every camera ``width x height x channels`` at ``rate_hz``."""

    width: int
    height: int
    rate_hz: float
    channels: int = 1
    bytes_per_channel: int = 1
    cameras_per_pair: int = 2
    pairs: int = 1

    def __post_init__(self) -> None:
        for name in ("width", "height", "channels", "bytes_per_channel", "cameras_per_pair", "pairs"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 1:
                raise CommsError(f"StereoStream.{name} must be a positive int, got {value!r}")
        if not self.rate_hz > 0:
            raise CommsError(f"StereoStream.rate_hz must be > 0, got {self.rate_hz!r}")

    @property
    def image_bytes(self) -> int:
        return self.width * self.height * self.channels * self.bytes_per_channel

    @property
    def bytes_per_s(self) -> float:
        return self.pairs * self.cameras_per_pair * self.image_bytes * self.rate_hz


def raw_stereo_load(streams: Iterable[StereoStream]) -> float:
    """Bytes per second the team would need to stream all its raw stereo images."""
    return float(sum(s.bytes_per_s for s in streams))


# The LRU navigation cameras of thesis 7.1 at the rate of thesis 8.4.
LRU_GUPPY_PRO_F125B = StereoStream(width=1292, height=964, rate_hz=14.3)
