"""The scene as one OpenUSD stage: Gaussians (UsdVol 3DGS particle field), collider, NavMesh, spawn, cameras."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from panoworld.core.conventions import CV_FROM_GL, quat_xyzw_from_wxyz
from panoworld.io.gaussian_set import Gaussians
from panoworld.io.splat_ply import used_sh_degree as sh_degree  # INRIA files may pad to degree 3 with zeros

UP_AXIS = "Z"
GRAVITY_M_S2 = 9.81
WORLD = "/World"
CAMERA_FOV_DEG = 90.0
"""Horizontal field of view of the animated pinhole camera (USD has no panoramic camera; the path is what matters)."""
_APERTURE_MM = 20.955  # USD's default horizontal aperture


@dataclass
class SceneParts:
    """Everything the stage holds, already in the asset frame except the Gaussians (canonical, under a transform)."""

    asset_from_canonical: np.ndarray
    """(4, 4) placed on the Gaussians prim, so that their SH radiance stays exact (no SH rotation)."""
    gaussians: Gaussians
    collider: tuple[np.ndarray, np.ndarray]
    """(vertices (V, 3) asset frame, faces (F, 3))."""
    navmesh: tuple[np.ndarray, np.ndarray]
    spawn: np.ndarray
    """(3,) asset frame."""
    camera_paths: list[np.ndarray]
    """Per path (N, 4, 4) world_from_cam poses in the canonical frame (OpenCV camera axes)."""
    fps: float
    capture_points: dict = field(default_factory=dict)
    """A home's capture points (build.capture_spawns: the agent's spawn and yaw in the asset frame), empty for one
    panorama."""


def _matrix(t: np.ndarray):
    from pxr import Gf

    return Gf.Matrix4d(np.asarray(t, np.float64).T.tolist())  # Gf: row vectors, translation in the last row


def _mesh(stage, path: str, vertices: np.ndarray, faces: np.ndarray, color: tuple, purpose: str):
    from pxr import UsdGeom, Vt

    m = UsdGeom.Mesh.Define(stage, path)
    m.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(vertices, np.float32)))
    m.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(faces), 3, np.int32)))
    m.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(faces, np.int32).reshape(-1)))
    m.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    m.CreateDoubleSidedAttr(True)
    m.CreateDisplayColorAttr([color])
    m.CreatePurposeAttr(purpose)
    lo, hi = (vertices.min(0), vertices.max(0)) if len(vertices) else (np.zeros(3), np.zeros(3))
    m.CreateExtentAttr([tuple(map(float, lo)), tuple(map(float, hi))])
    return m


def _gaussians(stage, path: str, g: Gaussians, xform: np.ndarray) -> dict:
    from pxr import UsdGeom, UsdVol, Vt

    g = g.numpy()
    p = UsdVol.ParticleField3DGaussianSplat.Define(stage, path)
    p.AddTransformOp().Set(_matrix(xform))
    means = np.ascontiguousarray(g.means, np.float32)
    # Everything in half precision (the schema's *h attributes): relative error <= 2^-11, far below what a render
    # shows. The positions stay in the canonical frame, centred on the capture point (the prim's transform places
    # them), so a position's error is <= 2^-11 of its distance from there: about 0.1 of a 1440-wide ERP pixel as
    # seen from the capture point, under a millimetre within 2 m of it.
    p.CreatePositionshAttr(Vt.Vec3hArray.FromNumpy(np.ascontiguousarray(means, np.float16)))
    q = np.asarray(g.quats, np.float64)
    q = q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-12)
    p.CreateOrientationshAttr(Vt.QuathArray.FromNumpy(np.ascontiguousarray(quat_xyzw_from_wxyz(q), np.float16)))
    p.CreateScaleshAttr(Vt.Vec3hArray.FromNumpy(np.ascontiguousarray(g.scales, np.float16)))
    p.CreateOpacitieshAttr(Vt.HalfArray.FromNumpy(np.ascontiguousarray(g.opacities, np.float16)))
    deg = sh_degree(g.sh_rest)
    n_coef = (deg + 1) ** 2
    sh = np.concatenate([g.sh_dc[:, None, :], g.sh_rest[:, : n_coef - 1]], axis=1)  # (N, n_coef, 3) per particle
    p.CreateRadianceSphericalHarmonicsDegreeAttr(deg)
    p.CreateRadianceSphericalHarmonicsCoefficientshAttr(
        Vt.Vec3hArray.FromNumpy(np.ascontiguousarray(sh.reshape(-1, 3), np.float16)))
    reach = 3.0 * np.asarray(g.scales, np.float32).max(1, keepdims=True) if len(means) else np.zeros((0, 1))
    lo, hi = ((means - reach).min(0), (means + reach).max(0)) if len(means) else (np.zeros(3), np.zeros(3))
    p.CreateExtentAttr([tuple(map(float, lo)), tuple(map(float, hi))])
    UsdGeom.Imageable(p).CreatePurposeAttr(UsdGeom.Tokens.render)
    return {"particles": int(len(means)), "sh_degree": deg}


def _camera(stage, path: str, poses_asset_gl: np.ndarray):
    from pxr import Gf, UsdGeom

    cam = UsdGeom.Camera.Define(stage, path)
    focal = _APERTURE_MM / 2 / np.tan(np.radians(CAMERA_FOV_DEG) / 2)
    cam.CreateFocalLengthAttr(float(focal))
    cam.CreateHorizontalApertureAttr(_APERTURE_MM)
    cam.CreateVerticalApertureAttr(_APERTURE_MM * 9 / 16)
    cam.CreateClippingRangeAttr(Gf.Vec2f(0.05, 100.0))
    op = cam.AddTransformOp()
    for i, t in enumerate(poses_asset_gl):
        op.Set(_matrix(t), float(i))


def write_scene_usd(path: Path, parts: SceneParts) -> dict:
    """Write the stage (the extension picks the format: .usdc binary crate, .usda text, .usdz package);
    returns counts. Stage metadata: metersPerUnit 1, kilogramsPerUnit 1, upAxis Z, defaultPrim /World."""
    from pxr import Gf, Kind, Tf, Usd, UsdGeom, UsdPhysics

    path = Path(path)
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    UsdPhysics.SetStageKilogramsPerUnit(stage, 1.0)
    world = UsdGeom.Xform.Define(stage, WORLD)
    stage.SetDefaultPrim(world.GetPrim())
    Usd.ModelAPI(world).SetKind(Kind.Tokens.assembly)

    scene = UsdPhysics.Scene.Define(stage, f"{WORLD}/PhysicsScene")
    scene.CreateGravityDirectionAttr(Gf.Vec3f(0.0, 0.0, -1.0))
    scene.CreateGravityMagnitudeAttr(GRAVITY_M_S2)

    info = _gaussians(stage, f"{WORLD}/Gaussians", parts.gaussians, parts.asset_from_canonical)

    col = _mesh(stage, f"{WORLD}/Collider", *parts.collider, (0.8, 0.3, 0.2), UsdGeom.Tokens.guide)
    UsdPhysics.CollisionAPI.Apply(col.GetPrim()).CreateCollisionEnabledAttr(True)
    UsdPhysics.MeshCollisionAPI.Apply(col.GetPrim()).CreateApproximationAttr(UsdPhysics.Tokens.none)
    _mesh(stage, f"{WORLD}/NavMesh", *parts.navmesh, (0.24, 0.78, 0.35), UsdGeom.Tokens.guide)

    spawn = UsdGeom.Xform.Define(stage, f"{WORLD}/Spawn")
    spawn.AddTranslateOp().Set(Gf.Vec3d(*map(float, parts.spawn)))
    if parts.capture_points:
        UsdGeom.Scope.Define(stage, f"{WORLD}/CapturePoints")
        used: set[str] = set()
        for name, cp in parts.capture_points.items():
            prim = _unique(Tf.MakeValidIdentifier(name), used)
            x = UsdGeom.Xform.Define(stage, f"{WORLD}/CapturePoints/{prim}")
            x.AddTranslateOp().Set(Gf.Vec3d(*map(float, cp["spawn"])))
            x.AddRotateZOp().Set(float(cp["yaw_deg"]))
            x.GetPrim().SetCustomDataByKey("panorama", name)

    UsdGeom.Scope.Define(stage, f"{WORLD}/Trajectory")
    frames = 0
    for k, poses in enumerate(parts.camera_paths):
        gl = parts.asset_from_canonical @ np.asarray(poses, np.float64) @ CV_FROM_GL
        _camera(stage, f"{WORLD}/Trajectory/Camera" + (f"_{k}" if k else ""), gl)
        frames = max(frames, len(poses))
    stage.SetTimeCodesPerSecond(float(parts.fps))
    stage.SetFramesPerSecond(float(parts.fps))
    stage.SetStartTimeCode(0.0)
    stage.SetEndTimeCode(float(max(frames - 1, 0)))
    stage.GetRootLayer().Save()
    info.update(collider_triangles=int(len(parts.collider[1])), navmesh_triangles=int(len(parts.navmesh[1])),
                cameras=len(parts.camera_paths), frames=frames)
    return info


def _unique(name: str, used: set[str]) -> str:
    """name, or name_2, name_3, ... where two panoramas' names map to one USD identifier."""
    out, k = name, 1
    while out in used:
        k += 1
        out = f"{name}_{k}"
    used.add(out)
    return out


def compliance_errors(path: Path) -> list[str]:
    """What usdchecker reports: every validator registered with usd-core (UsdValidation) run on the stage; one line
    per error or warning. (UsdUtils.ComplianceChecker, the older Python checker, is no longer in usd-core 26.)"""
    from pxr import Usd, UsdValidation

    stage = Usd.Stage.Open(str(path))
    ctx = UsdValidation.ValidationContext(UsdValidation.ValidationRegistry().GetOrLoadAllValidators())
    return [f"{e.GetType()}: {e.GetName()}: {e.GetMessage()}" for e in ctx.Validate(stage)]
