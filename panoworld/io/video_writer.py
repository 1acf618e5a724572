"""The video artifact's writer: PNG or JPEG frames, uint16 depth, video.json, an H.264 preview and the Foxglove MCAP,
encoded off the caller's thread."""

from __future__ import annotations

import json
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np

from panoworld.core.conventions import (
    check_erp_shape,
    check_pose,
    depth_to_mm,
    quat_wxyz_from_rotmat,
    quat_xyzw_from_wxyz,
    ros_world_from_cam,
)
from panoworld.core.shapes import check_shape
from panoworld.io.depth_png import encode_depth_png
from panoworld.io.rgb_image import RgbFormat, decode_rgb, encode_rgb, image_format_of, rgb_file_name
from panoworld.io.video import DEPTH_SCALE, VIDEO_FILE
from panoworld.io.video_mcap import (
    CAMERA_FRAME,
    MCAP_CODECS,
    MCAP_FILE,
    MCAP_X264_PRESET,
    TOPIC_COND_MASK,
    TOPIC_COND_RGB,
    TOPIC_DEPTH,
    TOPIC_POSE,
    TOPIC_RGB,
    TOPIC_TF,
    WORLD_FRAME,
    mcap_depth,
)

PREVIEW_FILE = "preview.mp4"
PREVIEW_CRF = "23"
"""x264's constant rate factor of the previews the writers encode themselves (conditions preview.mp4; video
preview.mp4 when it is not the MCAP's H.264 stream): x264's default, a preview, not an input of any stage."""


def _ns(index: int, fps: float) -> int:
    return int(round(index * 1e9 / fps))


class VideoWriter:
    """Streams frames into a video artifact directory: frames/%06d.png or .jpg (frame_format; JPEG of frame_quality),
    depth/%06d.png, preview.mp4, video.mcap and, with upscale > 1, upscaled/ (same format; an output only: later
    stages read frames/); close() writes video.json. Images are encoded by `workers` threads and the MCAP is written
    (in frame order) by one more, off the caller's thread; memory stays at a few frames whatever the length. The MCAP
    (a log for viewing) holds the frames and conditions once, at the generation size: mcap_codec h264 as two H.264
    streams of x264 CRF mcap_crf (a keyframe at least every 2 s), jpeg as JPEG of mcap_jpeg_quality (0: the files' own bytes).
    preview.mp4 is the MCAP's H.264 frame stream itself in an MP4 when the MCAP holds one and the frames are no wider
    than preview_max_width (no second encode), else its own x264 encode of CRF PREVIEW_CRF."""

    def __init__(
        self,
        out_dir: Path,
        *,
        height: int,
        width: int,
        fps: float,
        has_depth: bool,
        preview: bool = True,
        preview_max_width: int = 1920,
        mcap: bool = True,
        mcap_codec: str = "h264",
        mcap_crf: int = 28,
        mcap_jpeg_quality: int = 80,
        png_compression: int = 1,
        frame_format: RgbFormat | str = RgbFormat.PNG,
        frame_quality: int = 95,
        workers: int = 2,
        upscale: int = 1,
    ):
        check_erp_shape(height, width, "video frame")
        if upscale < 1:
            raise ValueError(f"{upscale=} must be >= 1")
        if fps <= 0:
            raise ValueError(f"{fps=} must be > 0")
        self.out_dir = Path(out_dir)
        self.height, self.width, self.fps, self.has_depth = height, width, float(fps), has_depth
        self.png_compression = png_compression
        self.frame_format = RgbFormat(frame_format)
        if not 1 <= frame_quality <= 100:
            raise ValueError(f"{frame_quality=} must be in [1, 100]")
        self.frame_quality = frame_quality
        if not 0 <= mcap_jpeg_quality <= 100:
            raise ValueError(f"{mcap_jpeg_quality=} must be in [0, 100]")
        if mcap_codec not in MCAP_CODECS:
            raise ValueError(f"{mcap_codec=} must be one of {MCAP_CODECS}")
        if not 0 <= mcap_crf <= 51:
            raise ValueError(f"{mcap_crf=} must be in [0, 51]")
        self.mcap_jpeg_quality, self.mcap_codec, self.mcap_crf = mcap_jpeg_quality, mcap_codec, mcap_crf
        self._h264: dict = {}  # topic -> H264Encoder, made at the topic's first frame
        self.upscale = upscale
        (self.out_dir / "frames").mkdir(parents=True, exist_ok=True)
        if upscale > 1:
            (self.out_dir / "upscaled").mkdir(exist_ok=True)
        if has_depth:
            (self.out_dir / "depth").mkdir(exist_ok=True)
        self.entries: list[dict] = []
        self.poses: list[np.ndarray] = []
        self._pool = ThreadPoolExecutor(max_workers=workers)
        self._mcap_pool = ThreadPoolExecutor(max_workers=1)  # one thread: messages stay in frame order
        self._pending: deque = deque()
        self._mp4 = None
        self._mp4_pool = ThreadPoolExecutor(max_workers=1)  # one thread: preview frames stay in order
        self._mp4_pending: deque = deque()
        self._preview_mux = None  # preview.mp4 muxed from the MCAP's H.264 frame stream
        if preview:
            import imageio_ffmpeg

            s = min(1.0, preview_max_width / width)
            self._preview_size = (max(2, int(round(width * s / 2)) * 2), max(2, int(round(height * s / 2)) * 2))
        if preview and mcap and mcap_codec == "h264" and self._preview_size == (width, height):
            from panoworld.io.h264 import Mp4Muxer

            self._preview_mux = Mp4Muxer(self.out_dir / PREVIEW_FILE, width, height, fps=self.fps)
        elif preview:
            self._mp4 = imageio_ffmpeg.write_frames(
                str(self.out_dir / PREVIEW_FILE), self._preview_size, fps=self.fps, codec="libx264",
                pix_fmt_out="yuv420p", quality=None, macro_block_size=2,
                output_params=["-preset", "veryfast", "-crf", PREVIEW_CRF], ffmpeg_log_level="error",
            )
            self._mp4.send(None)
        self._mcap = None
        if mcap:
            from mcap_protobuf.writer import Writer

            self._mcap_file = open(self.out_dir / MCAP_FILE, "wb")
            self._mcap = Writer(self._mcap_file)

    def add(
        self,
        rgb: np.ndarray,
        depth: np.ndarray | None,
        world_from_cam: np.ndarray,
        *,
        cond_rgb_png: bytes | None = None,
        cond_mask_png: bytes | None = None,
        cond_rgb: np.ndarray | None = None,
        upscaled: np.ndarray | None = None,
    ) -> None:
        """Append frame rgb (H, W, 3) uint8 with depth (H, W) metres (0 = unknown; required iff has_depth) at pose 4x4;
        the conditions' image bytes (PNG or JPEG, any size) go into the MCAP only, the RGB condition as its file's
        bytes cond_rgb_png or already decoded, cond_rgb (h, w, 3) uint8 (the H.264 stream takes it without decoding the
        bytes again; mcap_codec jpeg stores the bytes when given); upscaled (sH, sW, 3) uint8 (required iff the
        writer's upscale s > 1) goes to upscaled/ only."""
        H, W = self.height, self.width
        dims = check_shape("rgb", rgb, "H W 3", dtype=np.uint8, dims={"H": H, "W": W})
        s = self.upscale
        if (upscaled is not None) != (s > 1) or (upscaled is not None and upscaled.shape != (s * H, s * W, 3)):
            raise ValueError(f"upscaled {None if upscaled is None else upscaled.shape} but expected "
                             f"{(s * H, s * W, 3) if s > 1 else None} (writer upscale {s})")
        if self.has_depth != (depth is not None):
            raise ValueError(f"depth given: {depth is not None} but the writer has has_depth={self.has_depth}")
        if depth is not None:
            check_shape("depth", depth, "H W", dims=dims)
        check_pose(world_from_cam, "world_from_cam")
        i = len(self.entries)
        name = rgb_file_name(i, self.frame_format)
        entry = {"rgb": f"frames/{name}", "depth": None}
        if upscaled is not None:
            entry["upscaled"] = f"upscaled/{name}"
        if depth is not None:
            entry["depth"] = f"depth/{i:06d}.png"
        self.entries.append(entry)
        self.poses.append(np.asarray(world_from_cam, np.float64))
        # Everything below runs off the caller's thread (OpenCV, numpy and the pipe to ffmpeg release the GIL), so the
        # caller's next frame overlaps it; MCAP messages and preview frames stay in order.
        rgb = rgb.copy()
        if self._mp4 is not None:
            self._mp4_pending.append(self._mp4_pool.submit(self._send_preview, rgb))
        rgb_job = self._pool.submit(self._encode_write_rgb, rgb, self.out_dir / entry["rgb"])
        depth_job = None
        if depth is not None:
            depth_job = self._pool.submit(self._encode_depth, np.array(depth), self.out_dir / entry["depth"])
        up_job = None
        if upscaled is not None:
            up_job = self._pool.submit(self._encode_write_rgb, np.ascontiguousarray(upscaled),
                                       self.out_dir / entry["upscaled"])
        self._pending.append(self._mcap_pool.submit(
            self._finish, i, rgb_job, depth_job, up_job, self.poses[-1], cond_rgb_png, cond_mask_png, rgb, cond_rgb))
        while len(self._pending) > 2:
            self._pending.popleft().result()
        while len(self._mp4_pending) > 2:
            self._mp4_pending.popleft().result()

    def _send_preview(self, rgb: np.ndarray) -> None:
        small = rgb
        if self._preview_size != (self.width, self.height):
            small = cv2.resize(rgb, self._preview_size, interpolation=cv2.INTER_AREA)
        self._mp4.send(np.ascontiguousarray(small))

    def _encode_depth(self, depth: np.ndarray, path: Path) -> np.ndarray:
        """Depth (H, W) metres -> its uint16 millimetre PNG at path; returns the millimetres (the MCAP's)."""
        mm = depth_to_mm(depth)
        path.write_bytes(encode_depth_png(mm))
        return mm

    def _encode_write_rgb(self, rgb: np.ndarray, path: Path) -> bytes:
        data = encode_rgb(rgb, self.frame_format, quality=self.frame_quality, compression=self.png_compression)
        path.write_bytes(data)
        return data

    def _finish(self, i, rgb_job, depth_job, up_job, pose, cond_rgb_png, cond_mask_png, rgb, cond_rgb) -> None:
        png = rgb_job.result()
        mm = None if depth_job is None else depth_job.result()
        if up_job is not None:
            up_job.result()
        if self._mcap is not None:
            self._write_mcap(i, png, mm, pose, cond_rgb_png, cond_mask_png, rgb, cond_rgb)

    def _viewing_image(self, png: bytes | None, rgb: np.ndarray | None = None) -> tuple[bytes, str]:
        """(bytes, format) of an RGB image (its file's bytes png, or its pixels rgb when png is None) in the MCAP: JPEG
        of mcap_jpeg_quality, or the file's own bytes (PNG or JPEG as stored; lossless PNG of rgb) with 0."""
        q = self.mcap_jpeg_quality
        if q == 0:
            return (png, image_format_of(png)) if png is not None else (encode_rgb(rgb, RgbFormat.PNG), "png")
        bgr = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR) if rgb is not None else cv2.imdecode(
            np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
        ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, q])
        if not ok:
            raise ValueError("JPEG encoding failed")
        return buf.tobytes(), "jpeg"

    def _write_mcap(self, i, png, mm, world_from_cam, cond_rgb_png, cond_mask_png, rgb=None, cond_rgb=None) -> None:
        from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
        from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
        from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
        from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
        from google.protobuf.timestamp_pb2 import Timestamp

        t = _ns(i, self.fps)
        stamp = Timestamp(seconds=t // 1_000_000_000, nanos=t % 1_000_000_000)

        def put(topic, msg):
            self._mcap.write_message(topic, msg, log_time=t, publish_time=t, sequence=i)

        if self.mcap_codec == "h264":
            self._put_video(TOPIC_RGB, rgb if rgb is not None else decode_rgb(png, what="frame"))
        else:
            data, fmt = self._viewing_image(png, rgb)
            put(TOPIC_RGB, CompressedImage(timestamp=stamp, frame_id=CAMERA_FRAME, data=data, format=fmt))
        if mm is not None:
            mm = mcap_depth(mm)
            put(TOPIC_DEPTH, RawImage(timestamp=stamp, frame_id=CAMERA_FRAME, width=mm.shape[1], height=mm.shape[0],
                                      encoding="16UC1", step=2 * mm.shape[1], data=mm.tobytes()))
        if self.mcap_codec == "h264" and cond_rgb is not None:
            self._put_video(TOPIC_COND_RGB, cond_rgb)
        elif cond_rgb_png is not None and self.mcap_codec == "h264":
            self._put_video(TOPIC_COND_RGB, decode_rgb(cond_rgb_png, what="condition RGB"))
        elif cond_rgb_png is not None or cond_rgb is not None:
            data, fmt = self._viewing_image(cond_rgb_png, cond_rgb if cond_rgb_png is None else None)
            put(TOPIC_COND_RGB, CompressedImage(timestamp=stamp, frame_id=CAMERA_FRAME, data=data, format=fmt))
        if cond_mask_png is not None:
            put(TOPIC_COND_MASK, CompressedImage(timestamp=stamp, frame_id=CAMERA_FRAME, data=cond_mask_png, format="png"))
        ros = ros_world_from_cam(world_from_cam)
        x, y, z, w = quat_xyzw_from_wxyz(quat_wxyz_from_rotmat(ros[:3, :3]))
        tx, ty, tz = ros[:3, 3]
        tf = FrameTransform(timestamp=stamp, parent_frame_id=WORLD_FRAME, child_frame_id=CAMERA_FRAME)
        tf.translation.x, tf.translation.y, tf.translation.z = tx, ty, tz
        tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w = x, y, z, w
        put(TOPIC_TF, tf)
        pose = PoseInFrame(timestamp=stamp, frame_id=WORLD_FRAME)
        pose.pose.position.x, pose.pose.position.y, pose.pose.position.z = tx, ty, tz
        pose.pose.orientation.x, pose.pose.orientation.y, pose.pose.orientation.z, pose.pose.orientation.w = x, y, z, w
        put(TOPIC_POSE, pose)

    def _put_video(self, topic: str, rgb: np.ndarray | None) -> None:
        """Feed frame rgb (None: the end of the stream) to topic's H.264 stream and log the access units it yields."""
        from foxglove_schemas_protobuf.CompressedVideo_pb2 import CompressedVideo
        from google.protobuf.timestamp_pb2 import Timestamp

        from panoworld.io.h264 import H264_FORMAT, H264Encoder

        enc = self._h264.get(topic)
        if rgb is None:
            units = enc.flush() if enc is not None else []
        else:
            if enc is None:
                enc = self._h264[topic] = H264Encoder(rgb.shape[1], rgb.shape[0], fps=self.fps, crf=self.mcap_crf,
                                                      keyframe_interval=max(1, round(2 * self.fps)),
                                                      preset=MCAP_X264_PRESET)
            units = enc.encode(rgb)
        if topic == TOPIC_RGB and self._preview_mux is not None:
            self._preview_mux.write(units)
        for i, data, _key in units:
            t = _ns(i, self.fps)
            stamp = Timestamp(seconds=t // 1_000_000_000, nanos=t % 1_000_000_000)
            msg = CompressedVideo(timestamp=stamp, frame_id=CAMERA_FRAME, data=data, format=H264_FORMAT)
            self._mcap.write_message(topic, msg, log_time=t, publish_time=t, sequence=i)

    def close(self, meta: dict | None = None) -> dict:
        """Finish the frames, preview and MCAP and write video.json (meta adds keys such as backend/upscale); returns it."""
        while self._pending:
            self._pending.popleft().result()
        while self._mp4_pending:
            self._mp4_pending.popleft().result()
        self._pool.shutdown()
        self._mcap_pool.shutdown()
        self._mp4_pool.shutdown()
        if self._mp4 is not None:
            self._mp4.close()
            self._mp4 = None
        if self._mcap is not None:
            for topic in list(self._h264):
                self._put_video(topic, None)
            self._mcap.finish()
            self._mcap_file.close()
            self._mcap = None
        if self._preview_mux is not None:
            self._preview_mux.close()
            self._preview_mux = None
        doc = {
            "height": self.height,
            "width": self.width,
            "upscaled_height": self.height * self.upscale if self.upscale > 1 else None,
            "upscaled_width": self.width * self.upscale if self.upscale > 1 else None,
            "num_frames": len(self.entries),
            "fps": self.fps,
            **(meta or {}),
            "has_depth": self.has_depth,
            "depth_scale": DEPTH_SCALE,
            "frames": self.entries,
            "poses": [p.tolist() for p in self.poses],
        }
        (self.out_dir / VIDEO_FILE).write_text(json.dumps(doc, indent=1))
        return doc


def write_video(
    out_dir: Path, frames: np.ndarray, depth: np.ndarray | None, poses: np.ndarray, *, fps: float,
    meta: dict | None = None, **writer_kw,
) -> dict:
    """Write frames (T, H, W, 3) uint8, depth (T, H, W) metres or None and poses (T, 4, 4) as a video artifact."""
    dims = check_shape("frames", frames, "T H W 3")
    check_shape("poses", poses, "T 4 4", dims=dims)
    if depth is not None:
        check_shape("depth", depth, "T H W", dims=dims)
    T, H, W = frames.shape[:3]
    w = VideoWriter(Path(out_dir), height=H, width=W, fps=fps, has_depth=depth is not None, **writer_kw)
    for t in range(T):
        w.add(frames[t], None if depth is None else depth[t], poses[t])
    return w.close(meta)
