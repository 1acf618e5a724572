"""`runner.py view`: a scene's mesh, NavMesh, trajectory, COLMAP points and Gaussian splats in the browser (viser)."""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from panoworld.core.conventions import quat_wxyz_from_rotmat
from panoworld.core.errors import InputError, PanoWorldError
from panoworld.geometry.navmesh import load_navmesh
from panoworld.io.depth import load_depth_artifact
from panoworld.io.home import capture_poses
from panoworld.io.manifest import read_manifest
from panoworld.io.trajectory import load_clips, load_trajectory
from panoworld.io.video import read_video_doc
from panoworld.poses.estimate import load_poses

ARTIFACTS = "artifacts"


@dataclass(kw_only=True)
class ViewerParams:
    """What the viewer loads and where it listens."""

    host: str = "127.0.0.1"
    """Interface to bind (127.0.0.1: this machine only; 0.0.0.0 exposes the viewer to the network)."""
    port: int = 8080
    """TCP port of the viewer's web page."""
    mesh_rows: int = 256
    """The scene mesh is rebuilt from the depth artifact at most this many ERP rows high (browser memory)."""
    max_splats: int = 2_000_000
    """Keep at most this many Gaussians (the most opaque) in the browser."""
    frame_width: int = 512
    """Width of the video frame shown for the selected pose."""


def _read(reader, path: Path):
    """reader(path) (the artifact kind's one reader), or None when the artifact is missing or unreadable."""
    try:
        return reader(path)
    except (PanoWorldError, OSError, ValueError, KeyError, TypeError):
        return None


def load_scene_mesh(art: Path, max_rows: int):
    """The scene mesh (valid faces only) at most max_rows ERP rows high: rebuilt from the depth artifact, else mesh.ply."""
    from panoworld.geometry.erp_mesh import erp_mesh_from_depth, load_erp_mesh

    depth_dir = art / "depth"
    loaded = _read(load_depth_artifact, depth_dir)
    if loaded is not None:
        import cv2

        depth, valid, rgb = loaded
        depth = depth.astype(np.float32)
        if rgb.shape[:2] != depth.shape:
            rgb = cv2.resize(np.ascontiguousarray(rgb), (depth.shape[1], depth.shape[0]), interpolation=cv2.INTER_AREA)
        stride = max(1, int(np.ceil(depth.shape[0] / max_rows)))
        ratio = ((_read(read_manifest, art / "mesh") or {}).get("params") or {}).get("max_edge_ratio", 12.0)
        return erp_mesh_from_depth(depth, np.ascontiguousarray(rgb), valid, max_edge_ratio=ratio, stride=stride).valid_only()
    if (art / "mesh" / "mesh.ply").is_file():
        return load_erp_mesh(art / "mesh").valid_only()
    return None


def splat_arrays(g, max_splats: int) -> dict[str, np.ndarray]:
    """viser's splat inputs from our Gaussians: centers (N, 3), covariances (N, 3, 3), rgbs (N, 3) in [0, 1], opacities (N, 1)."""
    from panoworld.core.conventions import rotmat_from_quat_wxyz
    from panoworld.io.gaussian_set import SH_C0

    g = g.numpy() if hasattr(g, "numpy") else g
    keep = np.arange(len(g.means))
    if len(keep) > max_splats:
        keep = np.sort(np.argsort(-g.opacities)[:max_splats])
    R = rotmat_from_quat_wxyz(np.asarray(g.quats, np.float64)[keep])
    s2 = np.asarray(g.scales, np.float64)[keep] ** 2
    cov = np.einsum("nij,nj,nkj->nik", R, s2, R)
    return {
        "centers": np.asarray(g.means, np.float32)[keep],
        "covariances": cov.astype(np.float32),
        "rgbs": np.clip(0.5 + SH_C0 * np.asarray(g.sh_dc, np.float32)[keep], 0, 1),
        "opacities": np.asarray(g.opacities, np.float32)[keep, None],
    }


class SceneViewer:
    """A viser server showing one scene; `handles` maps layer names to their scene handles (tests toggle them)."""

    def __init__(self, scene_dir: Path, params: ViewerParams | None = None):
        import viser

        self.params = params or ViewerParams()
        self.scene_dir = Path(scene_dir)
        self.art = self.scene_dir / ARTIFACTS
        self.server = viser.ViserServer(host=self.params.host, port=self.params.port, verbose=False)
        self.server.scene.set_up_direction("-y")  # our world: gravity along +Y
        self.handles: dict[str, object] = {}
        self.loaded: dict[str, str] = {}
        self._frames: list[Path] = []
        self._poses: np.ndarray | None = None
        for name, fn in [("mesh", self._add_mesh), ("navmesh", self._add_navmesh), ("trajectory", self._add_trajectory),
                         ("captures", self._add_captures), ("points", self._add_points), ("splats", self._add_splats)]:
            try:
                self.loaded[name] = fn()
            except Exception as e:  # one unreadable artifact must not stop the viewer
                self.loaded[name] = f"unreadable: {type(e).__name__}: {e}"
        self._add_gui()
        cam = self.server.initial_camera
        cam.position, cam.look_at, cam.up = (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), (0.0, -1.0, 0.0)
        cam.fov = np.deg2rad(90.0)

    @property
    def url(self) -> str:
        return f"http://{self.params.host}:{self.server.get_port()}"

    def stop(self) -> None:
        self.server.stop()

    # ------------------------------------------------------------ layers

    def _add_mesh(self) -> str:
        import trimesh

        mesh = load_scene_mesh(self.art, self.params.mesh_rows)
        if mesh is None:
            return "missing (depth and mesh not run)"
        tm = trimesh.Trimesh(mesh.vertices, mesh.faces, vertex_colors=mesh.colors, process=False)
        has_splats = (self.art / "gaussians" / "gaussians.ply").is_file()
        self.handles["mesh"] = self.server.scene.add_mesh_trimesh("/mesh", tm, visible=not has_splats)
        return f"{len(mesh.faces)} faces"

    def _add_navmesh(self) -> str:
        nav = _read(load_navmesh, self.art / "navmesh")
        if nav is None:
            return "missing"
        xz = np.asarray(nav.vertices, np.float32).reshape(-1, 2)
        y = float(nav.floor_y) - 0.01
        v = np.stack([xz[:, 0], np.full(len(xz), y, np.float32), xz[:, 1]], 1)
        self.handles["navmesh"] = self.server.scene.add_mesh_simple(
            "/navmesh", v, np.asarray(nav.triangles, np.int32), color=(60, 220, 140), opacity=0.55, side="double")
        return f"{len(nav.triangles)} triangles"

    def _add_trajectory(self) -> str:
        planned = _read(load_trajectory, self.art / "trajectory")
        pa = _read(load_poses, self.art / "poses")
        recovered = None if pa is None else pa.world_from_cam
        vdoc = _read(read_video_doc, self.art / "video")
        self._frames = [] if vdoc is None else list(vdoc.rgb)
        if planned is not None and len(planned) > 1:  # each path from its predecessor (a home's cuts are no line)
            clips = _read(lambda p: load_clips(p, len(planned)), self.art / "trajectory") or [list(range(len(planned)))]
            pairs = np.array([(c[k], c[k + 1]) for c in clips for k in range(len(c) - 1)], np.int64).reshape(-1, 2)
            seg = np.stack([planned[pairs[:, 0], :3, 3], planned[pairs[:, 1], :3, 3]], 1).astype(np.float32)
            self.handles["planned"] = self.server.scene.add_line_segments("/trajectory/planned", seg, (255, 200, 0), thickness=0.01)
        poses = recovered if recovered is not None else planned
        if poses is None:
            return "missing"
        self._poses = poses
        reg = pa.registered if recovered is not None else None
        for i, T in enumerate(poses):
            ok = reg is None or (i < len(reg) and reg[i])
            self.server.scene.add_camera_frustum(
                f"/trajectory/frames/{i:04d}", fov=np.deg2rad(90.0), aspect=2.0, scale=0.06, thickness=1.5, thickness_units="screen",
                color=(40, 110, 220) if ok else (220, 40, 40), wxyz=quat_wxyz_from_rotmat(T[:3, :3]), position=T[:3, 3])
        self.handles["frustums"] = self.server.scene.add_frame("/trajectory/frames", show_axes=False)
        self.handles["current"] = self.server.scene.add_camera_frustum(
            "/trajectory/current", fov=np.deg2rad(90.0), aspect=2.0, scale=0.15, thickness=3.0, thickness_units="screen",
            color=(255, 120, 0),
            wxyz=quat_wxyz_from_rotmat(poses[0][:3, :3]), position=poses[0][:3, 3],
            image=self._frame_image(0, 256), format="jpeg")
        src = "recovered (poses.json)" if recovered is not None else "planned (trajectory.json)"
        return f"{len(poses)} {src} poses"

    def _add_captures(self) -> str:
        """A home's capture points (register artifact): a large frustum and a label at each."""
        captures = _read(capture_poses, self.art / "register") or {}
        if len(captures) < 2:
            return "one panorama" if captures else "missing"
        for name, T in captures.items():
            self.server.scene.add_camera_frustum(
                f"/captures/{name}", fov=np.deg2rad(90.0), aspect=2.0, scale=0.25, thickness=3.0,
                thickness_units="screen", color=(255, 176, 32), wxyz=quat_wxyz_from_rotmat(T[:3, :3]), position=T[:3, 3])
            self.server.scene.add_label(f"/captures/{name}/label", name, position=(0.0, -0.2, 0.0))
        self.handles["captures"] = self.server.scene.add_frame("/captures", show_axes=False)
        return f"{len(captures)} capture points ({', '.join(captures)})"

    def _add_points(self) -> str:
        sparse = self.art / "poses" / "sparse" / "0"
        if not (sparse / "points3D.bin").is_file():
            return "missing"
        import pycolmap

        rec = pycolmap.Reconstruction(str(sparse))
        if rec.num_points3D() == 0:
            return "0 points"
        pts = np.array([p.xyz for p in rec.points3D.values()], np.float32)
        cols = np.array([p.color for p in rec.points3D.values()], np.uint8)
        self.handles["points"] = self.server.scene.add_point_cloud("/colmap_points", pts, cols, point_size=0.01)
        return f"{len(pts)} points"

    def _add_splats(self) -> str:
        path = self.art / "gaussians" / "gaussians.ply"
        if not path.is_file():
            return "missing"
        from panoworld.io.splat_ply import read_gaussians_ply

        arrays = splat_arrays(read_gaussians_ply(path), self.params.max_splats)
        self.handles["splats"] = self.server.scene.add_gaussian_splats("/gaussians", **arrays)
        return f"{len(arrays['centers'])} Gaussians"

    # ------------------------------------------------------------ GUI

    def _add_gui(self) -> None:
        gui = self.server.gui
        gui.add_markdown(f"**{self.scene_dir.resolve().name}**  \n" + "  \n".join(f"{k}: {v}" for k, v in self.loaded.items()))
        for name in ("mesh", "navmesh", "planned", "frustums", "captures", "points", "splats"):
            h = self.handles.get(name)
            if h is None:
                continue
            box = gui.add_checkbox(name, bool(h.visible))

            @box.on_update
            def _(event, h=h, box=box) -> None:
                h.visible = box.value

        if self._poses is None:
            return
        n = len(self._poses)
        slider = gui.add_slider("frame", 0, max(n - 1, 1), 1, 0, disabled=n < 2)
        image = gui.add_image(self._frame_image(0), label="video frame", format="jpeg")
        self.handles["frame_slider"], self.handles["frame_image"] = slider, image

        @slider.on_update
        def _(event) -> None:
            self.select_frame(int(slider.value))

        button = gui.add_button("look from this frame")

        @button.on_click
        def _(event) -> None:
            T = self._poses[int(slider.value)]
            for client in self.server.get_clients().values():
                client.camera.position = T[:3, 3]
                client.camera.look_at = T[:3, 3] + T[:3, 2]  # the camera's +z (forward) axis
                client.camera.up_direction = -T[:3, 1]  # OpenCV y is down

    def _frame_image(self, i: int, width: int | None = None) -> np.ndarray:
        import cv2

        w = width or self.params.frame_width
        img = cv2.imread(str(self._frames[i]), cv2.IMREAD_COLOR) if i < len(self._frames) else None
        if img is None:
            return np.zeros((w // 2, w, 3), np.uint8)
        img = cv2.resize(img, (w, max(1, img.shape[0] * w // img.shape[1])), interpolation=cv2.INTER_AREA)
        return np.ascontiguousarray(img[..., ::-1])

    def select_frame(self, i: int) -> None:
        """Move the highlighted frustum to pose i and show video frame i."""
        T = self._poses[i]
        cur = self.handles["current"]
        cur.position, cur.wxyz = T[:3, 3], quat_wxyz_from_rotmat(T[:3, :3])
        cur.image = self._frame_image(i, 256)  # the ERP frame drawn flat in the frustum, as a thumbnail
        self.handles["frame_image"].image = self._frame_image(i)


def is_loopback(host: str) -> bool:
    """True for an address (or `localhost`) only this machine can reach."""
    import ipaddress

    if host.strip().lower() in ("localhost", "localhost."):
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False  # a host name: it resolves to whatever interface it names


def serve_warnings(host: str, requested_port: int, served_port: int) -> list[str]:
    """Loud lines for what the user may not expect: a non-loopback host, a requested port that was taken."""
    out = []
    if not is_loopback(host):
        out.append(f"WARNING: --host {host} is not a loopback address: this scene (mesh, frames, Gaussians) is served "
                   "without authentication to every machine that can reach this one; use --host 127.0.0.1 to keep it local")
    if served_port != requested_port:
        out.append(f"WARNING: port {requested_port} is taken; serving on port {served_port} instead (the URL below)")
    return out


def check_bind(host: str, port: int, timeout_s: float = 1.5) -> None:
    """Refuse, in one line and within timeout_s, a port outside 1..65535, a host that does not resolve, or an address
    this machine cannot listen on (the server would otherwise fail in its own thread and never exit)."""
    import socket
    import threading

    if not 1 <= port <= 65535:
        raise InputError(f"--port {port}: expected a TCP port in 1..65535 (default {ViewerParams().port})")
    found: list = []

    def resolve() -> None:
        try:
            found.append(socket.getaddrinfo(host, None, type=socket.SOCK_STREAM))
        except (OSError, UnicodeError) as e:
            found.append(e)

    worker = threading.Thread(target=resolve, daemon=True)
    worker.start()
    worker.join(timeout_s)
    if not found or isinstance(found[0], Exception) or not found[0]:
        why = "no answer in time" if not found else str(found[0])
        raise InputError(f"--host {host}: cannot resolve it ({why}); give an address of this machine such as 127.0.0.1")
    family, _, _, _, addr = found[0][0]
    try:
        with socket.socket(family, socket.SOCK_STREAM) as s:
            s.bind((addr[0], 0))
    except OSError as e:
        raise InputError(f"--host {host}: cannot listen on {addr[0]} ({e.strerror}); give an address of this machine "
                         "such as 127.0.0.1") from None


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="python runner.py view", description=__doc__)
    ap.add_argument("scene", type=Path, help="scene directory (its artifacts/ are shown; missing stages are skipped)")
    d = ViewerParams()
    ap.add_argument("--port", type=int, default=d.port, help=f"TCP port (default: {d.port})")
    ap.add_argument("--host", default=d.host, help=f"interface to bind (default: {d.host}, this machine only)")
    ap.add_argument("--mesh-rows", type=int, default=d.mesh_rows, help=f"mesh resolution in ERP rows (default: {d.mesh_rows})")
    ap.add_argument("--max-splats", type=int, default=d.max_splats, help=f"most Gaussians sent to the browser (default: {d.max_splats})")
    return ap


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if not (args.scene / ARTIFACTS).is_dir():
        print(f"error: {args.scene}: no artifacts/ directory (run `python runner.py run {args.scene}` first)", file=sys.stderr)
        return 2
    params = ViewerParams(host=args.host, port=args.port, mesh_rows=args.mesh_rows, max_splats=args.max_splats)
    check_bind(params.host, params.port)
    try:
        import viser  # noqa: F401
    except ImportError:
        print("error: the viewer needs viser: pip install -e .", file=sys.stderr)
        return 2
    try:
        viewer = SceneViewer(args.scene, params)
    except OSError as e:
        raise InputError(f"--host {params.host} --port {params.port}: cannot serve there ({e.strerror or e}); "
                         "give another --port or --host") from None
    for k, v in viewer.loaded.items():
        print(f"{k:<11} {v}")
    for line in serve_warnings(params.host, params.port, viewer.server.get_port()):
        print(line, file=sys.stderr, flush=True)
    print(f"viewer: {viewer.url}  (Ctrl-C to stop)", flush=True)
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        viewer.stop()
    return 0
