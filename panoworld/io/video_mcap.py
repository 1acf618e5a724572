"""The video artifact's Foxglove MCAP (video.mcap): topics, subsampled depth, and the readers that decode it."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from panoworld.core.conventions import quat_wxyz_from_xyzw, rotmat_from_quat_wxyz, world_from_ros_world

MCAP_FILE = "video.mcap"

# MCAP topics (Foxglove protobuf schemas). Depth is a foxglove.RawImage '16UC1' in millimetres (0 = unknown) of every
# MCAP_DEPTH_STRIDE-th pixel of every MCAP_DEPTH_STRIDE-th row, rounded to MCAP_DEPTH_STEP_MM, which Foxglove's Image
# panel shows with a colour map (depth/ holds the exact full frames); RGB frames and conditions are H.264 foxglove.CompressedVideo (mcap_codec h264) or
# JPEG foxglove.CompressedImage (jpeg: of mcap_jpeg_quality, or the files' own bytes, PNG or JPEG, with 0); condition
# masks are PNG.
MCAP_DEPTH_STRIDE = 4
"""The MCAP's depth keeps one pixel in 4 x 4 (a viewing log: a 720x1440 frame's depth as 180x360)."""
MCAP_DEPTH_STEP_MM = 20
"""The MCAP's depth in steps of 2 cm (still '16UC1' millimetres): on the demo 30 % of the compressed bytes of exact
millimetres; a colour map over 0-10 m has steps of 4 cm."""
MCAP_X264_PRESET = "superfast"
"""x264's preset of the MCAP's H.264 streams: on the demo's 720x1440 frames ~15 ms a frame; veryfast at CRF 26 gives
the same PSNR to frames/ in 0.9x the bytes for 1.7x the encoding CPU."""
MCAP_CODECS = ("h264", "jpeg")
"""How video.mcap stores the RGB frames and conditions: H.264 streams (about a third of JPEG 80's bytes) or JPEG images."""
TOPIC_RGB = "/camera/rgb"
TOPIC_DEPTH = "/camera/depth"
TOPIC_COND_RGB = "/conditions/rgb"
TOPIC_COND_MASK = "/conditions/mask"
TOPIC_TF = "/tf"
TOPIC_POSE = "/camera/pose"
WORLD_FRAME = "world"
CAMERA_FRAME = "camera"


def mcap_depth(mm: np.ndarray) -> np.ndarray:
    """A frame's uint16 millimetres (H, W) -> the MCAP's (one pixel in MCAP_DEPTH_STRIDE^2, to the nearest
    MCAP_DEPTH_STEP_MM, 0 = unknown kept and nothing known made 0), little-endian uint16."""
    step = MCAP_DEPTH_STEP_MM
    src = mm[::MCAP_DEPTH_STRIDE, ::MCAP_DEPTH_STRIDE].astype(np.int32)
    out = np.clip((src + step // 2) // step * step, step, 65535 // step * step)
    return np.ascontiguousarray(np.where(src == 0, 0, out), "<u2")


def read_mcap(path: Path) -> dict[str, list]:
    """Decode a video.mcap: {topic: [decoded message, ...]} in log-time order (foxglove protobuf messages)."""
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    out: dict[str, list] = {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _schema, channel, _message, proto in reader.iter_decoded_messages(log_time_order=True):
            out.setdefault(channel.topic, []).append(proto)
    return out


def world_from_cam_from_mcap(tf) -> np.ndarray:
    """A foxglove FrameTransform / Pose of the camera in the ROS world -> our world_from_cam (4, 4)."""
    if "translation" in tf.DESCRIPTOR.fields_by_name:
        t, q = tf.translation, tf.rotation
    else:
        pose = tf.pose if "pose" in tf.DESCRIPTOR.fields_by_name else tf
        t, q = pose.position, pose.orientation
    ros = np.eye(4)
    ros[:3, :3] = rotmat_from_quat_wxyz(quat_wxyz_from_xyzw(np.array([q.x, q.y, q.z, q.w])))
    ros[:3, 3] = [t.x, t.y, t.z]
    return world_from_ros_world() @ ros


def raw_image_array(msg) -> np.ndarray:
    """A foxglove RawImage ('16UC1', 'mono8', 'rgb8' or '32FC1') -> numpy array (H, W[, C])."""
    dtypes = {"16UC1": ("<u2", 1), "mono8": ("u1", 1), "8UC1": ("u1", 1), "rgb8": ("u1", 3), "32FC1": ("<f4", 1)}
    if msg.encoding not in dtypes:
        raise ValueError(f"RawImage encoding {msg.encoding!r} not one of {sorted(dtypes)}")
    dt, c = dtypes[msg.encoding]
    item = np.dtype(dt).itemsize
    rows = np.frombuffer(msg.data, np.uint8).reshape(msg.height, msg.step)[:, : msg.width * c * item]
    arr = np.ascontiguousarray(rows).view(dt).reshape(msg.height, msg.width, c)
    return arr[..., 0] if c == 1 else arr
