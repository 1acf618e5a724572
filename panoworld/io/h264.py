"""H.264 access units of an RGB frame stream (PyAV's libx264), as foxglove.CompressedVideo wants them."""

from __future__ import annotations

from fractions import Fraction

import numpy as np

H264_FORMAT = "h264"
"""foxglove.CompressedVideo format: Annex B, one access unit per message, SPS/PPS in every keyframe, no B-frames."""


class H264Encoder:
    """Encodes (H, W, 3) uint8 RGB frames into H.264 access units (Annex B byte stream, yuv420p, no B-frames, an IDR
    with its SPS and PPS at least every keyframe_interval frames). x264 looks ahead: a frame's access unit may come out
    of a later encode() call or of flush(), tagged with its frame index. An odd width or height gets its last column or
    row repeated (yuv420p needs even sizes)."""

    def __init__(self, width: int, height: int, *, fps: float, crf: int = 23, keyframe_interval: int = 32,
                 preset: str = "veryfast"):
        import av

        self.width, self.height = width, height
        c = av.CodecContext.create("libx264", "w")
        c.width, c.height, c.pix_fmt = width + width % 2, height + height % 2, "yuv420p"
        rate = Fraction(fps).limit_denominator(1001)
        c.framerate, c.time_base = rate, 1 / rate
        c.gop_size = max(1, int(keyframe_interval))
        c.max_b_frames = 0
        c.options = {"crf": str(int(crf)), "preset": preset, "bf": "0"}
        self._ctx = c
        self._next = 0

    def encode(self, rgb: np.ndarray) -> list[tuple[int, bytes, bool]]:
        """Frame rgb (H, W, 3) uint8 -> the (frame index, access unit bytes, keyframe) that came out."""
        import av

        if rgb.shape != (self.height, self.width, 3) or rgb.dtype != np.uint8:
            raise ValueError(f"frame {rgb.shape} {rgb.dtype} but the stream is ({self.height}, {self.width}, 3) uint8")
        if self.width % 2 or self.height % 2:
            rgb = np.pad(rgb, ((0, self.height % 2), (0, self.width % 2), (0, 0)), mode="edge")
        frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(rgb), format="rgb24")
        frame.pts = self._next
        self._next += 1
        return self._units(self._ctx.encode(frame))

    def flush(self) -> list[tuple[int, bytes, bool]]:
        """The access units still inside the encoder; the stream ends."""
        return self._units(self._ctx.encode(None))

    @staticmethod
    def _units(packets) -> list[tuple[int, bytes, bool]]:
        return [(int(p.pts), bytes(p), bool(p.is_keyframe)) for p in packets]


class Mp4Muxer:
    """An MP4 file of an H264Encoder's access units as they are (no second encode), opened at the first unit; the
    avcC header comes from the first keyframe's SPS and PPS."""

    def __init__(self, path, width: int, height: int, *, fps: float):
        self.path, self.width, self.height = path, width, height
        self._rate = Fraction(fps).limit_denominator(1001)
        self._out = self._stream = None

    def write(self, units: list[tuple[int, bytes, bool]]) -> None:
        """Mux (frame index, access unit, keyframe) triples, in decoding order."""
        import av

        if self._out is None and units:
            self._out = av.open(str(self.path), "w", format="mp4")
            self._stream = self._out.add_stream("h264", rate=self._rate)
            self._stream.width, self._stream.height = self.width + self.width % 2, self.height + self.height % 2
            self._stream.pix_fmt = "yuv420p"
        for i, data, key in units:
            packet = av.Packet(data)
            packet.pts = packet.dts = i
            packet.time_base = 1 / self._rate
            packet.stream = self._stream
            packet.is_keyframe = key
            self._out.mux(packet)

    def close(self) -> None:
        if self._out is not None:
            self._out.close()
            self._out = None
