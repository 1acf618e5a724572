"""The asset in a real physics engine (PyBullet): collider.obj as a static triangle mesh and an upright agent capsule
dropped at the spawn, swept along the planned path, and pushed into a wall."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

HZ = 240.0
"""Simulation steps per second."""
PUSH_FORCE_N = 300.0
"""The most horizontal force BulletScene.push drives the capsule with (half its weight at 60 kg)."""
MAX_CLOSEST_POINTS = 30_000
"""Most closest points BulletScene.clearance trusts from one PyBullet query."""


@dataclass
class Agent:
    radius: float
    height: float
    """Total height of the capsule (feet to head), metres."""
    step_height: float = 0.2
    """The walking sweep lifts the capsule's feet this high (steps below it are walked over, as in the NavMesh)."""


class BulletScene:
    """PyBullet (DIRECT, no GUI) with gravity -9.81 along z, the collider loaded from its OBJ file as a static concave
    triangle mesh and one capsule agent (axis z) kept upright."""

    def __init__(self, collider_obj: Path, agent: Agent, mass_kg: float = 60.0):
        import pybullet as pb

        self.pb, self.agent, self.mass = pb, agent, mass_kg
        self.cid = pb.connect(pb.DIRECT)
        pb.setGravity(0, 0, -9.81, physicsClientId=self.cid)
        pb.setTimeStep(1.0 / HZ, physicsClientId=self.cid)
        shape = pb.createCollisionShape(pb.GEOM_MESH, fileName=str(collider_obj), flags=pb.GEOM_FORCE_CONCAVE_TRIMESH,
                                        physicsClientId=self.cid)
        if shape < 0:
            raise ValueError(f"{collider_obj}: PyBullet could not load it as a triangle mesh")
        self.static = pb.createMultiBody(0, shape, physicsClientId=self.cid)
        cap = pb.createCollisionShape(pb.GEOM_CAPSULE, radius=agent.radius, height=agent.height - 2 * agent.radius,
                                      physicsClientId=self.cid)
        self.body = pb.createMultiBody(mass_kg, cap, basePosition=[0, 0, 10], physicsClientId=self.cid)
        pb.changeDynamics(self.body, -1, lateralFriction=0.0, restitution=0.0, physicsClientId=self.cid)
        pb.changeDynamics(self.static, -1, restitution=0.0, physicsClientId=self.cid)

    def close(self) -> None:
        self.pb.disconnect(physicsClientId=self.cid)

    def __enter__(self) -> BulletScene:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def static_aabb(self) -> tuple[np.ndarray, np.ndarray]:
        lo, hi = self.pb.getAABB(self.static, physicsClientId=self.cid)
        return np.array(lo), np.array(hi)

    def place(self, feet: np.ndarray, velocity=(0.0, 0.0, 0.0)) -> None:
        """Capsule with its lowest point at `feet`, upright, moving at `velocity`."""
        c = np.asarray(feet, np.float64) + [0, 0, self.agent.height / 2]
        self.pb.resetBasePositionAndOrientation(self.body, c.tolist(), [0, 0, 0, 1], physicsClientId=self.cid)
        self.pb.resetBaseVelocity(self.body, list(velocity), [0, 0, 0], physicsClientId=self.cid)

    def feet(self) -> np.ndarray:
        c, _ = self.pb.getBasePositionAndOrientation(self.body, physicsClientId=self.cid)
        return np.array(c) - [0, 0, self.agent.height / 2]

    def velocity(self) -> np.ndarray:
        return np.array(self.pb.getBaseVelocity(self.body, physicsClientId=self.cid)[0])

    def step(self, horizontal: np.ndarray | None = None) -> None:
        """One step; the agent stays upright (no spin) and, if given, keeps this horizontal velocity (a controller)."""
        v = self.velocity()
        if horizontal is not None:
            v[:2] = horizontal
        feet = self.feet()
        self.place(feet, v)
        self.pb.stepSimulation(physicsClientId=self.cid)

    def push(self, horizontal: np.ndarray, max_force_n: float = PUSH_FORCE_N) -> None:
        """One step driven towards this horizontal velocity by a force of at most max_force_n, upright: a motor, which
        an obstacle stops (a velocity forced every step instead pushes it through a real mesh's thin furniture)."""
        v = self.velocity()
        force = self.mass * HZ * (np.asarray(horizontal, np.float64) - v[:2])
        force *= min(1.0, max_force_n / max(float(np.linalg.norm(force)), 1e-12))
        feet = self.feet()
        self.place(feet, v)
        self.pb.applyExternalForce(self.body, -1, [float(force[0]), float(force[1]), 0.0],
                                   (feet + [0, 0, self.agent.height / 2]).tolist(), self.pb.WORLD_FRAME,
                                   physicsClientId=self.cid)
        self.pb.stepSimulation(physicsClientId=self.cid)

    def clearance(self, max_m: float = 1.0) -> float:
        """Signed distance from the capsule to the collider (< 0: penetration), capped at max_m, to a millimetre.
        PyBullet returns zero-filled points, or crashes, when more than some tens of thousands of triangles lie within
        the distance asked (a dense real mesh near its nadir): the distance asked starts at 1 mm, doubles while
        nothing answers and is bisected while too many do."""
        empty, full, r = None, None, min(0.001, max_m)
        while True:
            pts = self.pb.getClosestPoints(self.body, self.static, r, physicsClientId=self.cid)
            if len(pts) > MAX_CLOSEST_POINTS:
                full = r
            elif pts:
                return min(p[8] for p in pts)
            elif r >= max_m:
                return max_m
            else:
                empty = r
            if full is None:
                r = min(2 * r, max_m)
            elif full - (empty or 0.0) < 1e-3:
                if empty is None:
                    raise ValueError(f"more than {MAX_CLOSEST_POINTS} collider triangles within a millimetre of the "
                                     "capsule: decimate the collider")
                return empty
            else:
                r = 0.5 * (full + (empty or 0.0))

    def cast(self, origins: np.ndarray, ends: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Ray fractions (1 = no hit) and hit normals against the collider, PyBullet's own ray test."""
        res = self.pb.rayTestBatch(np.asarray(origins).tolist(), np.asarray(ends).tolist(), physicsClientId=self.cid)
        frac = np.array([r[2] if r[0] == self.static else 1.0 for r in res])
        normal = np.array([r[4] for r in res], np.float64)
        return frac, normal


def drop_test(scene: BulletScene, spawn: np.ndarray, drop_m: float = 0.3, seconds: float = 2.5) -> dict:
    """Drop the capsule from drop_m above the spawn; it must come to rest with its feet on the floor."""
    spawn = np.asarray(spawn, np.float64)
    scene.place(spawn + [0, 0, drop_m])
    n, window = int(seconds * HZ), min(0.5, seconds / 2)
    before = scene.feet()
    for i in range(n):
        scene.step(np.zeros(2))
        if i == n - int(window * HZ) - 1:
            before = scene.feet()
    feet = scene.feet()
    # mean speed over the last 0.5 s: contacts on a triangle mesh jitter by a few mm/s from step to step
    return {"rest_height_m": float(feet[2] - spawn[2]), "speed_m_s": float(np.linalg.norm(feet - before) / window),
            "drift_m": float(np.linalg.norm(feet[:2] - spawn[:2])), "clearance_m": scene.clearance()}


def walk_test(scene: BulletScene, path_xy: np.ndarray, floor_z: float, max_step_m: float = 0.02) -> dict:
    """Sweep the capsule (feet lifted by the agent's step height) along the path, sampled every max_step_m: the
    least signed distance to the collider over the sweep (> 0: it never penetrates)."""
    p = np.asarray(path_xy, np.float64).reshape(-1, 2)
    pts = [p[0]]
    for a, b in zip(p[:-1], p[1:]):
        n = max(int(np.ceil(np.linalg.norm(b - a) / max_step_m)), 1)
        pts += [a + (b - a) * (k / n) for k in range(1, n + 1)]
    z = floor_z + scene.agent.step_height
    dists = []
    for xy in pts:
        scene.place(np.array([xy[0], xy[1], z]))
        dists.append(scene.clearance())
    d = np.array(dists)
    return {"samples": len(d), "min_clearance_m": float(d.min()), "worst_sample": int(d.argmin()),
            "length_m": float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())}


def drop_ok(r: dict, rest_tol_m: float = 0.02, speed_tol_m_s: float = 0.01) -> bool:
    """A drop_test result at rest: still (speed below speed_tol_m_s) with its feet within rest_tol_m of the spawn."""
    return r["speed_m_s"] < speed_tol_m_s and abs(r["rest_height_m"]) < rest_tol_m


def nearest_wall(scene: BulletScene, spawn: np.ndarray, directions: int = 36, reach_m: float = 8.0,
                 flat_m: float = 0.1, max_incidence_deg: float = 20.0) -> dict | None:
    """The horizontal direction from the spawn whose obstacle is nearest, over rays at several heights of the capsule
    (feet to head), among those whose rays all stop within flat_m of one another on surfaces facing the spawn within
    max_incidence_deg (a wall, met nearly head-on; "flat": True), else among all that are blocked at every height
    ("flat": False); None when no direction is blocked at every height within reach_m (no wall around). A frictionless
    capsule pushed into furniture or at a slant slides along it."""
    a = scene.agent
    heights = np.linspace(0.05, a.height - 0.05, 8)
    scene.place(np.array([0.0, 0.0, 1e4]))  # out of the rays' way: a ray from inside the capsule stops at it
    best: dict[bool, dict] = {}
    for k in range(directions):
        ang = 2 * np.pi * k / directions
        d = np.array([np.cos(ang), np.sin(ang), 0.0])
        o = np.asarray(spawn, np.float64)[None] + heights[:, None] * [0, 0, 1]
        frac, normal = scene.cast(o, o + reach_m * d)
        if np.all(frac < 1.0):
            n = normal[:, :2].mean(axis=0)  # a real mesh's triangles are noisy: their mean faces where the wall does
            facing = -float(n @ d[:2]) / max(float(np.linalg.norm(n)), 1e-12)
            dist = float(frac.min() * reach_m)
            flat = bool(np.ptp(frac) * reach_m <= flat_m and facing >= np.cos(np.radians(max_incidence_deg)))
            if flat not in best or dist < best[flat]["distance_m"]:
                best[flat] = {"direction": d, "distance_m": dist, "normal": normal[int(frac.argmin())], "flat": flat}
    return best.get(True, best.get(False))


def wall_test(scene: BulletScene, spawn: np.ndarray, speed_m_s: float = 0.5, extra_s: float = 2.0) -> dict:
    """Rest the capsule at the spawn, then push it (BulletScene.push) horizontally at speed_m_s towards the nearest
    wall for longer than it needs to get there: it must stop at the wall (or at an obstacle beside the way there), not
    pass through it; deepest_m: its least clearance on the way, every 20th of a second (see wall_ok)."""
    spawn = np.asarray(spawn, np.float64)
    wall = nearest_wall(scene, spawn)
    if wall is None:
        raise ValueError("no wall around the spawn within reach")
    d, dist = wall["direction"], wall["distance_m"]
    drop_test(scene, spawn, drop_m=0.05, seconds=0.5)
    start = scene.feet()
    steps = int(((dist + 1.0) / speed_m_s + extra_s) * HZ)
    deepest = np.inf
    for i in range(steps):
        scene.push(speed_m_s * d[:2])
        if i % int(HZ / 20) == 0:
            deepest = min(deepest, scene.clearance())
    end = scene.feet()
    travel = float(np.dot(end - start, d))
    stop_at = dist - scene.agent.radius
    scene.place(end + [0, 0, 0.03])  # lifted off the floor: what is left in contact is the obstacle that stopped it
    contact = scene.clearance()
    return {"wall_distance_m": dist, "expected_travel_m": stop_at, "travel_m": travel,
            "gap_m": stop_at - travel, "fell_m": float(start[2] - end[2]), "obstacle_contact_m": contact,
            "deepest_m": float(deepest), "direction": d.tolist(), "flat": wall["flat"]}


def wall_ok(r: dict, tol_m: float = 0.05) -> bool:
    """Stopped by an obstacle (in contact with something other than the floor), never beyond the wall the centre line
    meets (an obstacle beside that line may stop the capsule's body earlier), never deeper than tol_m into anything on
    the way, not sunk into the floor."""
    return (r["obstacle_contact_m"] < 0.02 and r["gap_m"] > -tol_m and r["deepest_m"] > -tol_m
            and r["fell_m"] < tol_m)
