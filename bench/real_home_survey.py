"""A home's registration against its survey (ZInD survey.json: 2D capture positions and yaws): registered count,
pairwise capture-point distance error, relative yaw error and the position error after a best 2D rigid alignment;
every pair the registration tried by layout, with its layout pose's error against the survey; with --floor-fits, every
pair's floor fit against the survey (right or chance); and with --floor-evidence,
per pair of panoramas the registration did not join, how many floor-image matches agree with the survey's relative
pose (the evidence any floor fit could find there); and with --subsets N, the home registered again as N random
subsets of its panoramas (3 to 10 each, fewer than all, from the depth artifact beside REGISTER_ARTIFACT, default
RegisterOptions), each against the survey: a subset whose registered panoramas break 0.25 m of pairwise distance
error or 2 deg of yaw error is misplaced (a home without the panoramas that join or check its rooms, as a user's
capture may be); and with --rolls N --home HOME, the home registered again N times from its inputs with every panorama
turned by its own random azimuth (where its seam falls), each draw against the survey (with --rows R, from its
panoramas resized to R rows; with --exposure G, each panorama's exposure scaled by its own random gain within G
times; with --tilt D, each panorama and its depth tilted by D degrees about its own random horizontal axis; with
--rename, the panoramas renamed in a random order; with --mirror, each panorama and its depth flipped left to right,
a mirror-image home with the same geometry and other keypoints; --rows, --exposure, --tilt, --rename or --mirror alone:
once).

`python bench/real_home_survey.py REGISTER_ARTIFACT SURVEY_JSON [--json] [--floor-fits] [--floor-evidence] [--subsets N]
[--rolls N] [--rows R] [--exposure G] [--tilt D] [--rename] [--mirror] [--home HOME] [--seed S]` prints them;
`compare_to_survey` is the function the real-home benchmark imports."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np

from panoworld.geometry.upright import yaw_of


def _wrap_deg(a: np.ndarray) -> np.ndarray:
    return (np.asarray(a) + 180.0) % 360.0 - 180.0


def compare_to_survey(world_from_cam: dict[str, np.ndarray], survey: dict) -> dict:
    """Registration ({NAME: 4x4 world_from_cam}, world y = gravity, as panoramas.json holds) against survey (the parsed
    survey.json: {"panos": {NAME: {"position_m_xy", "yaw_deg", ...}}}) -> dict:

    - registered / panoramas: how many surveyed panoramas have a pose; unregistered: their names.
    - pairs: per registered pair, the horizontal capture-point distance (estimated, surveyed, |error| m) and the
      relative yaw error (deg): (yaw_b - yaw_a) estimated against (yaw_deg_b - yaw_deg_a) surveyed, wrapped.
      Our yaw turns camera x (right) towards z (forward) about y (down); ZInD's yaw_deg turns the same way.
    - dist_err_m_median / _max, yaw_err_deg_median / _max over the pairs (None with fewer than 2 registered).
    - aligned_err_m_median / _max: per registered panorama, the horizontal position error after the best 2D rigid
      alignment of the estimated positions (x, z) onto the surveyed ones; ZInD's plan frame is mirrored against
      (x, z), so the alignment is a rotation composed with that mirror.
    """
    panos = survey["panos"]
    names = sorted(n for n in panos if n in world_from_cam)
    out: dict = {"panoramas": len(panos), "registered": len(names),
                 "unregistered": sorted(n for n in panos if n not in world_from_cam), "pairs": []}
    keys = ("dist_err_m_median", "dist_err_m_max", "yaw_err_deg_median", "yaw_err_deg_max", "aligned_err_m_median",
            "aligned_err_m_max")
    if len(names) < 2:
        return {**out, **dict.fromkeys(keys)}
    est = {n: np.asarray(world_from_cam[n], np.float64) for n in names}
    xz = {n: est[n][[0, 2], 3] for n in names}
    xy = {n: np.asarray(panos[n]["position_m_xy"], np.float64) for n in names}
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            d_est, d_sur = float(np.linalg.norm(xz[b] - xz[a])), float(np.linalg.norm(xy[b] - xy[a]))
            yaw_est = np.degrees(yaw_of(est[b][:3, :3]) - yaw_of(est[a][:3, :3]))
            yaw_sur = panos[b]["yaw_deg"] - panos[a]["yaw_deg"]
            out["pairs"].append({"a": a, "b": b, "dist_est_m": round(d_est, 4), "dist_survey_m": round(d_sur, 4),
                                 "dist_err_m": round(abs(d_est - d_sur), 4),
                                 "yaw_err_deg": round(float(abs(_wrap_deg(yaw_est - yaw_sur))), 3)})
    dist = np.array([p["dist_err_m"] for p in out["pairs"]])
    yaw = np.array([p["yaw_err_deg"] for p in out["pairs"]])
    P = np.array([xz[n][::-1] for n in names])  # (z, x): the mirror between our plan and ZInD's
    Q = np.array([xy[n] for n in names])
    Pc, Qc = P - P.mean(0), Q - Q.mean(0)
    U, _, Vt = np.linalg.svd(Pc.T @ Qc)
    D = np.diag([1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt  # Pc @ R ~ Qc, a proper rotation
    err = np.linalg.norm(Pc @ R - Qc, axis=1)
    out["aligned_err_m"] = {n: round(float(e), 4) for n, e in zip(names, err)}
    return {**out, "dist_err_m_median": float(np.median(dist)), "dist_err_m_max": float(dist.max()),
            "yaw_err_deg_median": float(np.median(yaw)), "yaw_err_deg_max": float(yaw.max()),
            "aligned_err_m_median": float(np.median(err)), "aligned_err_m_max": float(err.max())}


def row_pose_error(row: dict, kind: str, true_a_from_b: np.ndarray) -> tuple[float, float]:
    """How far a registration.json pair row's `kind` pose ("floor" or "layout": its a_from_b as KIND_xz_m and
    KIND_yaw_deg) lies from true_a_from_b (4, 4): (metres on the floor, degrees of yaw)."""
    x, z = row[f"{kind}_xz_m"]
    dyaw = _wrap_deg(row[f"{kind}_yaw_deg"] - np.degrees(yaw_of(true_a_from_b[:3, :3])))
    return float(np.hypot(x - true_a_from_b[0, 3], z - true_a_from_b[2, 3])), abs(float(dyaw))


def layout_pairs(registration: dict, survey: dict) -> list[dict]:
    """Per pair that registration (the parsed registration.json) says layout tried: the best and best distinct
    score, their ratio, the layout pose's distance and yaw error against the survey, the edge it became or why not."""
    from bench_real_home import survey_poses  # bench/, beside this script (it imports this module)

    world = survey_poses(survey)
    rows = []
    for r in registration["pairs"]:
        if "layout_score" not in r:
            continue
        err_m, yaw_err = row_pose_error(r, "layout", np.linalg.inv(world[r["a"]]) @ world[r["b"]])
        rows.append({"a": r["a"], "b": r["b"], "score": r["layout_score"], "second": r["layout_second"],
                     "ratio": round(r["layout_score"] / max(r["layout_second"], 1e-9), 3),
                     "err_m": round(err_m, 3), "yaw_err_deg": round(yaw_err, 2),
                     "edge": r.get("edge"), "refused": r.get("layout_refused", "")})
    return rows


def floor_fits(registration: dict, survey: dict, *, least: int = 5) -> list[dict]:
    """Every floor fit of at least `least` inliers among registration's pair rows (registration.json's "pairs", both
    panoramas surveyed) against the survey: inliers, the runner-up's (floor_second), how far the fit lies from the
    survey's pose (m, deg), right (within MISPLACED_M and MISPLACED_DEG: the survey is good to about 0.1 m between
    rooms) or a chance fit, the edge it became and why it was refused. Right fits first, then most inliers."""
    from bench_real_home import survey_poses

    world = survey_poses(survey)
    rows = []
    for r in registration["pairs"]:
        if r.get("floor_inliers", 0) < least or "floor_xz_m" not in r or r["a"] not in world or r["b"] not in world:
            continue
        err_m, yaw_err = row_pose_error(r, "floor", np.linalg.inv(world[r["a"]]) @ world[r["b"]])
        rows.append({"a": r["a"], "b": r["b"], "inliers": r["floor_inliers"], "second": r.get("floor_second", 0),
                     "err_m": round(err_m, 3), "yaw_err_deg": round(yaw_err, 2),
                     "right": err_m <= MISPLACED_M and yaw_err <= MISPLACED_DEG, "edge": r.get("edge"),
                     "refused": r.get("floor_refused", "")})
    return sorted(rows, key=lambda r: (not r["right"], -r["inliers"]))


def floor_evidence(depth_artifact: Path, survey: dict, registered: set[str], pairs: list[dict] = ()) -> list[dict]:
    """Per pair of panoramas not both registered: the floor views' matches (the register stage's floor_view on the
    depth artifact's cleaned panoramas, rig excluded, default RegisterOptions; floor_pair's nearest-neighbour matches
    both ways) that agree with the survey's relative pose within 8 cm on the floor, 15 deg in keypoint orientation
    and 0.6 octaves in size, and, from the registration's pair rows (registration.json's "pairs"), the pair's floor
    fit: its inliers, how far it lies from the survey's pose (m, deg: the survey itself is good to about 0.1 m
    between rooms, so a fit can agree with the truth and keep no match within 8 cm of the survey's pose) and why it
    was refused. Fits near the survey (MISPLACED_M, MISPLACED_DEG) first, then most agreeing."""
    from bench_real_home import survey_poses

    from panoworld.geometry.floor_view import floor_matches
    from panoworld.geometry.resize import rgbd_at_height
    from panoworld.io.home import RIG_MASK_PNG, home_depth_dirs, load_sources
    from panoworld.io.images import read_rig_mask
    from panoworld.register.floor import floor_support, panorama_floor_view
    from panoworld.register.layout import manhattan_frame
    from panoworld.register.options import RegisterOptions
    from panoworld.register.pairwise import grow_exclusion

    o = RegisterOptions()
    world = survey_poses(survey)
    dirs = home_depth_dirs(depth_artifact)
    names, rgbs, depths = load_sources(dirs, world)
    views = {}
    for n in names:
        rig = dirs[n] / RIG_MASK_PNG
        small = rgbd_at_height(rgbs[n], depths[n], o.height)[1]
        views[n] = panorama_floor_view(rgbs[n], small, grow_exclusion(read_rig_mask(rig) if rig.is_file() else None),
                                       manhattan_frame(small), o)
    fits = {(r["a"], r["b"]): r for r in pairs if "floor_xz_m" in r}
    rows = []
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            va, vb = views[a], views[b]
            if (a in registered and b in registered) or va is None or vb is None or len(va.xz) < 2 or len(vb.xz) < 2:
                continue
            gt = np.linalg.inv(world[a]) @ world[b]
            m = floor_matches(va, vb, both_ways=True)  # the matches floor_pair fits
            row = {"a": a, "b": b, "distance_m": round(float(np.hypot(gt[0, 3], gt[2, 3])), 2),
                   "agreeing": floor_support(va, vb, gt, matches=m), "matches": len(m)}
            fit, true = fits.get((a, b)), gt
            if fit is None and (b, a) in fits:  # the row holds b_from_a
                fit, true = fits[b, a], np.linalg.inv(gt)
            if fit is not None:
                err_m, yaw_err = row_pose_error(fit, "floor", true)
                row.update(fit_inliers=fit["floor_inliers"], refused=fit.get("floor_refused", ""),
                           fit_err_m=round(err_m, 3), fit_yaw_err_deg=round(yaw_err, 2))
            rows.append(row)

    def near(r: dict) -> bool:
        return r.get("fit_err_m", np.inf) <= MISPLACED_M and r.get("fit_yaw_err_deg", np.inf) <= MISPLACED_DEG

    return sorted(rows, key=lambda r: (not near(r), -r["agreeing"], r["distance_m"]))


MISPLACED_M, MISPLACED_DEG = 0.25, 2.0
"""A registration that breaks either (pairwise distance error m, relative yaw error deg) has a panorama misplaced."""


def subset_registrations(depth_artifact: Path, survey: dict, sets: int, seed: int = 0) -> list[dict]:
    """The home's panoramas (depth_artifact: the depth stage's artifact of a home) registered again as `sets` random
    subsets of 3 to 10, fewer than all (none for a home of 3 or fewer; register_depth_dirs, default RegisterOptions),
    each against survey (compare_to_survey over its surveyed panoramas): per subset its panoramas, the registered
    ones, the errors and whether it is misplaced."""

    import tempfile

    from panoworld.io.home import home_depth_dirs
    from panoworld.register.artifact import register_depth_dirs
    from panoworld.register.options import RegisterOptions

    dirs = home_depth_dirs(depth_artifact)
    names = sorted(dirs)
    rng = np.random.default_rng(seed)
    most = min(10, len(names) - 1)
    rows: list[dict] = []
    for i in range(sets if most >= 3 else 0):
        sub = sorted(rng.choice(names, size=int(rng.integers(3, most + 1)), replace=False).tolist())
        with tempfile.TemporaryDirectory() as td:
            register_depth_dirs({n: dirs[n] for n in sub}, None, RegisterOptions(), Path(td))
            world = {n: np.asarray(T) for n, T in json.loads((Path(td) / "panoramas.json").read_text()).items()}
        part = {"panos": {n: v for n, v in survey["panos"].items() if n in sub}}
        r = compare_to_survey(world, part)
        d, y = r["dist_err_m_max"], r["yaw_err_deg_max"]
        rows.append({"panoramas": sub, "registered": sorted(world), "dist_err_m_max": d, "yaw_err_deg_max": y,
                     "misplaced": d is not None and (d > MISPLACED_M or y > MISPLACED_DEG)})
        print(f"subset {i + 1}/{sets}: {len(world)} of {len(sub)} registered", file=sys.stderr, flush=True)
    return rows


def expose(rgb: np.ndarray, gain: float, balance: np.ndarray) -> np.ndarray:
    """rgb (H, W, 3) uint8 as if captured with its exposure times gain and its white balance times balance (3,): on
    linear light (a 2.2 gamma), clipped as a camera clips."""
    lin = (rgb.astype(np.float32) / 255.0) ** 2.2 * (gain * np.asarray(balance, np.float32))
    return np.clip(np.clip(lin, 0.0, 1.0) ** (1 / 2.2) * 255.0 + 0.5, 0, 255).astype(np.uint8)


def tilt(rgb: np.ndarray, depth: np.ndarray, deg: float, azimuth: float) -> tuple[np.ndarray, np.ndarray]:
    """rgb (H, W, 3) and its ray depth (h, w) as captured by the same camera tilted by deg about the horizontal axis
    at azimuth (radians, from the camera's z towards x): rgb resampled bicubic, the depth as the library levels one
    (geometry.level.levelled_depth: bilinear on smooth surfaces, nearest at edges; a ray's distance is the same from
    a camera turned about its centre)."""
    import cv2

    from panoworld.core.conventions import erp_dirs, erp_pixel_from_dir
    from panoworld.geometry.level import levelled_depth

    tilted_from_level = cv2.Rodrigues(np.array([np.sin(azimuth), 0.0, np.cos(azimuth)]) * np.radians(deg))[0]
    h, w = rgb.shape[:2]
    u, v = erp_pixel_from_dir(erp_dirs(h, w).reshape(-1, 3).astype(np.float64) @ tilted_from_level, h, w)
    out = cv2.remap(rgb, ((u - 0.5) % w).reshape(h, w).astype(np.float32),
                    np.clip(v - 0.5, 0, h - 1).reshape(h, w).astype(np.float32), cv2.INTER_CUBIC,
                    borderMode=cv2.BORDER_WRAP)
    return out, levelled_depth(depth, tilted_from_level)


def roll_registrations(home: Path, survey: dict, draws: int, seed: int = 0, size: int | None = None,
                       turn: bool = True, exposure: float = 1.0, rename: bool = False,
                       tilt_deg: float = 0.0, mirror: bool = False) -> list[dict]:
    """The home (panoramas/, depths/) registered again `draws` times with each panorama and its depth turned about
    gravity by its own random azimuth (a whole number of depth columns, so both move exactly; not with turn=False),
    and resized to `size` rows first (area; the depth by the same factor, nearest), through the depth and
    register stages at default settings (`runner.py run COPY --until register`); the survey's yaws turned with
    them. exposure > 1: each panorama's exposure also scaled by its own gain, log-uniform in [1 / exposure,
    exposure], and its white balance by its own factor per channel in [0.95, 1.05] (expose), as a tour's auto
    exposure differs from room to room. tilt_deg: each panorama and its depth tilted by it about its own random
    horizontal axis (tilt), as an unlevelled camera captures. rename: the panoramas named capture_000, capture_001,
    ... in a random order (the capture order and the first name, which sets the world frame and breaks ties between
    groups), the result read back under their own names. mirror: each panorama and its depth flipped left to right
    (azimuth a -> -a): the mirror image of the home, its survey mirrored with it (x -> -x, yaw -> -yaw), whose
    distances and relative yaws (negated) are the home's while its keypoints differ. Per draw: the registered
    panoramas, the errors and whether it is misplaced. Where a panorama's seam falls, the capture's size, its
    exposure, its name and its handedness are arbitrary; the registration
    should not depend on them (beyond which of two equally large groups is registered)."""
    import subprocess
    import tempfile

    import cv2
    from bench_rig_real import vary

    from panoworld.io.depth import read_depth, read_panorama

    rng = np.random.default_rng(seed)
    names = sorted(p.stem for p in (home / "depths").iterdir() if p.suffix == ".npy")
    rows: list[dict] = []
    for i in range(draws):
        with tempfile.TemporaryDirectory() as td:
            copy = Path(td) / "home"
            (copy / "panoramas").mkdir(parents=True)
            (copy / "depths").mkdir()
            turned = {"panos": {}}
            order = rng.permutation(len(names)) if rename else np.arange(len(names))
            alias = {n: f"capture_{order[j]:03d}" if rename else n for j, n in enumerate(names)}
            for n in names:
                src = next(p for p in (home / "panoramas").iterdir() if p.stem == n)
                rgb, depth, k = vary(read_panorama(src), read_depth(home / "depths" / f"{n}.npy"),
                                     rng if turn else None, size, src)
                if tilt_deg:
                    rgb, depth = tilt(rgb, depth, tilt_deg, float(rng.uniform(0, 2 * np.pi)))
                if exposure > 1:
                    rgb = expose(rgb, float(np.exp(rng.uniform(-1, 1) * np.log(exposure))), rng.uniform(0.95, 1.05, 3))
                if mirror:
                    rgb, depth = np.ascontiguousarray(rgb[:, ::-1]), np.ascontiguousarray(depth[:, ::-1])
                cv2.imwrite(str(copy / "panoramas" / f"{alias[n]}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
                np.save(copy / "depths" / f"{alias[n]}.npy", depth)
                if n in survey["panos"]:
                    v = turned["panos"][n] = dict(survey["panos"][n])
                    v["yaw_deg"] -= 360.0 * k / depth.shape[1]
                    if mirror:
                        v.update(yaw_deg=-v["yaw_deg"], position_m_xy=[-v["position_m_xy"][0], v["position_m_xy"][1]])
            proc = subprocess.run([sys.executable, str(Path(__file__).resolve().parents[1] / "runner.py"), "run",
                                   str(copy), "--until", "register"], capture_output=True, text=True)
            if proc.returncode:
                raise SystemExit(f"draw {i + 1}: runner.py run failed:\n{proc.stderr[-2000:]}")
            out = copy / "artifacts" / "register"
            named = {a: n for n, a in alias.items()}
            world = {named[a]: np.asarray(T) for a, T in json.loads((out / "panoramas.json").read_text()).items()}
        r = compare_to_survey(world, turned)
        d, y = r["dist_err_m_max"], r["yaw_err_deg_max"]
        rows.append({"registered": sorted(world), "unregistered": r["unregistered"], "dist_err_m_max": d,
                     "yaw_err_deg_max": y, "misplaced": d is not None and (d > MISPLACED_M or y > MISPLACED_DEG)})
        print(f"draw {i + 1}/{draws}: {len(world)} of {len(names)} registered", file=sys.stderr, flush=True)
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("register", type=Path, help="a register artifact (holds panoramas.json)")
    ap.add_argument("survey", type=Path, help="survey.json")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--floor-evidence", action="store_true",
                    help="per pair not both registered, the floor matches that agree with the survey (reads the depth "
                         "artifact beside REGISTER_ARTIFACT)")
    ap.add_argument("--floor-fits", action="store_true",
                    help="every pair's floor fit of 5 or more inliers against the survey: right or chance")
    ap.add_argument("--subsets", type=int, default=0, metavar="N",
                    help="register N random subsets of the home's panoramas again (3-10 each, from the depth artifact "
                         "beside REGISTER_ARTIFACT) and report each against the survey")
    ap.add_argument("--rolls", type=int, default=0, metavar="N",
                    help="with --home: register the home N times again, each panorama and its depth turned by a random "
                         "azimuth (the depth and register stages at default settings), and report each draw")
    ap.add_argument("--home", type=Path, help="--rolls, --rows: the home's input folder (panoramas/, depths/)")
    ap.add_argument("--rows", type=int, default=None, metavar="R",
                    help="with --home: register the home from its panoramas resized to R rows (each --rolls draw, or "
                         "once as given)")
    ap.add_argument("--exposure", type=float, default=1.0, metavar="G",
                    help="with --home: each panorama's exposure scaled by its own random gain in [1/G, G] and its "
                         "white balance by up to 5 %% per channel (each --rolls draw, or once)")
    ap.add_argument("--tilt", type=float, default=0.0, metavar="D",
                    help="with --home: each panorama and its depth tilted by D degrees about its own random horizontal "
                         "axis (each --rolls draw, or once)")
    ap.add_argument("--rename", action="store_true",
                    help="with --home: the panoramas renamed in a random order in each draw (capture order, first name)")
    ap.add_argument("--mirror", action="store_true",
                    help="with --home: each panorama and its depth flipped left to right (a mirror-image home)")
    ap.add_argument("--seed", type=int, default=0, help="the subsets' and the draws' random seed")
    args = ap.parse_args()
    poses = {n: np.asarray(T) for n, T in json.loads((args.register / "panoramas.json").read_text()).items()}
    survey = json.loads(args.survey.read_text())
    r = compare_to_survey(poses, survey)
    reg = args.register / "registration.json"
    r["layout_pairs"] = layout_pairs(json.loads(reg.read_text()), survey) if reg.is_file() else []
    if args.floor_fits:
        r["floor_fits"] = floor_fits(json.loads(reg.read_text()), survey) if reg.is_file() else []
    if args.floor_evidence:
        rows = json.loads(reg.read_text()).get("pairs", []) if reg.is_file() else []
        r["floor_evidence"] = floor_evidence(args.register.parent / "depth", survey, set(poses), rows)
    if args.subsets:
        r["subsets"] = subset_registrations(args.register.parent / "depth", survey, args.subsets, args.seed)
    if args.rolls or args.rows or args.exposure > 1 or args.rename or args.tilt or args.mirror:
        if args.home is None:
            ap.error("--rolls, --rows, --exposure, --tilt, --rename and --mirror need --home (the home's panoramas/ and "
                     "depths/)")
        r["rolls"] = roll_registrations(args.home, survey, args.rolls or 1, args.seed, args.rows, turn=bool(args.rolls),
                                        exposure=args.exposure, rename=args.rename, tilt_deg=args.tilt,
                                        mirror=args.mirror)
    if args.json:
        print(json.dumps(r, indent=1))
        return 0

    def f(x, spec):
        return "-" if x is None else format(x, spec)

    print("| registered | distance error m median / max | yaw error deg median / max | aligned position error m "
          "median / max | unregistered |")
    print("| --- | --- | --- | --- | --- |")
    print(f"| {r['registered']} of {r['panoramas']} | {f(r['dist_err_m_median'], '.3f')} / "
          f"{f(r['dist_err_m_max'], '.3f')} | {f(r['yaw_err_deg_median'], '.2f')} / {f(r['yaw_err_deg_max'], '.2f')} "
          f"| {f(r['aligned_err_m_median'], '.3f')} / {f(r['aligned_err_m_max'], '.3f')} | "
          f"{', '.join(r['unregistered']) or '-'} |")
    if r["layout_pairs"]:
        print("\n| layout pair | score | best distinct | ratio | error m | yaw error deg | edge | refused |")
        print("| --- | --- | --- | --- | --- | --- | --- | --- |")
        for p in r["layout_pairs"]:
            print(f"| {p['a']}-{p['b']} | {p['score']:.0f} | {p['second']:.0f} | {p['ratio']:.2f} | {p['err_m']:.2f} | "
                  f"{p['yaw_err_deg']:.1f} | {p['edge'] or '-'} | {p['refused']} |")
    if args.floor_fits:
        fits = r["floor_fits"]
        right = [x for x in fits if x["right"]]
        chance = [x for x in fits if not x["right"]]
        print(f"\nfloor fits of 5 or more inliers: {len(right)} right (inliers "
              f"{min((x['inliers'] for x in right), default=0)}-{max((x['inliers'] for x in right), default=0)}, "
              f"runner-ups at most {max((x['second'] / x['inliers'] for x in right), default=0):.0%} of the fit's), "
              f"{len(chance)} chance fits (inliers at most {max((x['inliers'] for x in chance), default=0)})")
        print("| pair | inliers | runner-up | from the survey m / deg | right | edge | refused |")
        print("| --- | --- | --- | --- | --- | --- | --- |")
        for x in fits:
            print(f"| {x['a']}-{x['b']} | {x['inliers']} | {x['second']} | {x['err_m']:.3f} / {x['yaw_err_deg']:.2f} | "
                  f"{'yes' if x['right'] else '-'} | {x['edge'] or '-'} | {(x['refused'] or '-')[:90]} |")
    if args.floor_evidence:
        ev = r["floor_evidence"]
        print(f"\nfloor evidence over the {len(ev)} pairs not both registered (matches agreeing with the survey; a floor "
              "edge needs 6 distinct inliers, and another pair across its cut below 11):")
        print("| pair | distance m | agreeing matches | matches | floor fit inliers | fit from the survey m / deg | "
              "refused |")
        print("| --- | --- | --- | --- | --- | --- | --- |")
        for p in ev[:15]:
            print(f"| {p['a']}-{p['b']} | {p['distance_m']:.2f} | {p['agreeing']} | {p['matches']} | "
                  f"{f(p.get('fit_inliers'), 'd')} | {f(p.get('fit_err_m'), '.3f')} / {f(p.get('fit_yaw_err_deg'), '.2f')}"
                  f" | {(p.get('refused') or '-')[:90]} |")
    if args.subsets:
        rows = r["subsets"]
        print(f"\n{len(rows)} random subsets registered again (seed {args.seed}): "
              f"{sum(len(x['registered']) for x in rows)} of {sum(len(x['panoramas']) for x in rows)} panoramas "
              f"registered, {sum(x['misplaced'] for x in rows)} subsets misplaced (> {MISPLACED_M} m or "
              f"> {MISPLACED_DEG} deg)")
        print("| panoramas | registered | distance error m max | yaw error deg max | misplaced |")
        print("| --- | --- | --- | --- | --- |")
        for x in rows:
            print(f"| {', '.join(x['panoramas'])} | {', '.join(x['registered'])} | {f(x['dist_err_m_max'], '.3f')} | "
                  f"{f(x['yaw_err_deg_max'], '.2f')} | {'yes' if x['misplaced'] else '-'} |")
    if "rolls" in r:
        rows = r["rolls"]
        what = f"draws of random azimuths (seed {args.seed})" if args.rolls else "registration from the inputs"
        what += f", exposures within {args.exposure:g}x" if args.exposure > 1 else ""
        what += f", tilted {args.tilt:g} deg" if args.tilt else ""
        what += ", renamed in a random order" if args.rename else ""
        what += ", mirrored" if args.mirror else ""
        print(f"\n{len(rows)} {what}{f' at {args.rows} rows' if args.rows else ''}: "
              f"{sum(len(x['registered']) for x in rows)} of {len(rows) * r['panoramas']} surveyed panoramas "
              f"registered, {sum(x['misplaced'] for x in rows)} draws misplaced")
        print("| draw | registered | unregistered | distance error m max | yaw error deg max | misplaced |")
        print("| --- | --- | --- | --- | --- | --- |")
        for i, x in enumerate(rows):
            print(f"| {i + 1} | {len(x['registered'])} | {', '.join(x['unregistered']) or '-'} | "
                  f"{f(x['dist_err_m_max'], '.3f')} | {f(x['yaw_err_deg_max'], '.2f')} | {'yes' if x['misplaced'] else '-'} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
