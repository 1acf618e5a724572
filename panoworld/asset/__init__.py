"""The simulation-ready asset: the scene in OpenUSD (Gaussians, collider, NavMesh, spawn, cameras) + collider.obj."""

from panoworld.asset.build import (
    ASSET_JSON,
    COLLIDER_OBJ,
    SCENE_USD,
    build_asset,
    read_asset_doc,
    spawn_point,
    trajectory_paths,
    write_asset_doc,
)
from panoworld.asset.collider import Collider, collision_mesh, write_obj

__all__ = [
    "ASSET_JSON", "COLLIDER_OBJ", "SCENE_USD", "Collider", "build_asset", "read_asset_doc", "write_asset_doc", "collision_mesh", "spawn_point",
    "trajectory_paths", "write_obj",
]
