"""Options of panorama registration (light to import: the register stage's Params nest them)."""

from __future__ import annotations

from dataclasses import dataclass

from panoworld.core.params import param
from panoworld.register.pair_select import ALL_PAIRS_UP_TO

BEYOND_SHARE = 0.9
"""A weak floor edge lies between its rooms when at least this share of its inlier matches (and RegisterOptions'
floor_beyond_rooms of them) lie beyond both rooms' walls: floor both panoramas see only through openings."""


@dataclass(kw_only=True)
class RegisterOptions:
    """How panoramas are matched and when a pairwise estimate is trusted."""

    height: int = param(720, ge=64)
    """Panoramas and depths are resampled to at most this many rows before feature detection."""
    max_features: int = param(16000, ge=100)
    """SIFT keypoints per panorama (shared by its six cube-face views)."""
    all_pairs_up_to: int = param(ALL_PAIRS_UP_TO, ge=2)
    """Homes of at most this many panoramas try every pair. Larger homes try 8 pairs per panorama (its next in name
    order and its most alike by appearance), then the pairs across the groups those leave apart (a floor edge the
    images do not confirm joins none: graph.bridging_groups), nearest in name order first, up to 8 more per panorama
    (panoworld/register/pair_select.py)."""
    max_error_m: float = param(0.05, gt=0)
    """RANSAC inlier threshold: 3D distance in metres between matched depth-backed points."""
    min_inliers: int = param(12, ge=3)
    """A pair needs at least this many RANSAC inliers."""
    min_consistency: float = param(0.9, ge=0, le=1)
    """A pair needs at least this free-space consistency of its dense depth maps at the estimated pose (see
    PairResult.consistency): rejects wrong poses that a few repeated-texture matches agree on."""
    min_overlap: float = param(0.02, ge=0, le=1)
    """A pair needs at least this fraction of depth pixels seen by both panoramas."""
    refine_height: int = param(256, ge=16)
    """Rows of the depth maps (valid-weighted area average) the ICP refinement runs on."""
    refine_iterations: int = param(15, ge=0)
    """Point-to-plane ICP steps on the dense depth maps after RANSAC (0 = RANSAC only), starting with pairs within
    2 max_error_m and ending within 1 cm; a wider start locked onto surfaces a wall thickness away."""
    bearing_threshold_px: float = param(1.5, gt=0)
    """Bearing-only pairs (those the depth-backed fit does not trust): RANSAC inlier threshold on the angle of a matched
    ray to its epipolar plane, in ERP pixels of the resampled panorama (180 / rows degrees each)."""
    min_bearing_inliers: int = param(20, ge=5)
    """A bearing-only pair needs at least this many inliers."""
    depth_yaw_tol_deg: float = param(2.0, gt=0)
    """A depth-backed pose must agree with the pair's bearing-only estimate of the same matches (when that keeps
    >= min_bearing_inliers) on the yaw within this: a dense consistency test passes trivially where one depth holds
    little more than a floor and ceiling disc, the images do not."""
    depth_direction_tol_deg: float = param(10.0, gt=0)
    """... on the direction of the baseline within this (where the depth-backed baseline is longer than
    2 max_error_m) ..."""
    depth_scale_tol: float = param(0.1, gt=0)
    """... and, where the bearing-only estimate is metric (>= min_scale_support), on the baseline length within this
    fraction."""
    min_scale_support: int = param(8, ge=1)
    """A bearing-only pair is metric when at least this many of its triangulated points have depths in both views
    that agree on the scale; with fewer it only gives the direction of the baseline."""
    floor: bool = True
    """Also register pairs from their floors (panoworld/register/floor.py): each panorama's lower hemisphere projected
    onto its floor plane at metric scale (camera height from its depth), SIFT on those top-down images and a 1-point
    rigid RANSAC over (x, z, yaw). Floor seen through a doorway from both sides matches where the perspective of the
    panoramas does not."""
    floor_radius_m: float = param(6.0, gt=0)
    """The floor images cover x, z within this of the camera."""
    floor_cell_m: float = param(0.015, gt=0)
    """Floor image pixel size (metres)."""
    floor_supersample: int = param(3, ge=1, le=4)
    """Samples per floor image pixel side, averaged: within about 2 m of the camera a 1.5 cm pixel spans several
    pixels of a 2048-wide panorama, and one sample per pixel aliases the floor's texture differently in each view."""
    floor_along_walls: bool = True
    """Lay each floor image's axes along its room's walls (manhattan_frame; the camera's axes where it has none): the
    floor images of one home then differ by quarter turns, under which SIFT finds the same keypoints again, whatever
    the azimuth each panorama's seam fell at."""
    floor_threshold_m: float = param(0.05, gt=0)
    """Floor RANSAC inlier threshold: distance on the floor between matched keypoints (metres)."""
    floor_ratio: float = param(1.0, gt=0, le=1)
    """Lowe ratio of the floor image matches (1 = every keypoint's nearest neighbour: the floor RANSAC's inliers must
    also agree in keypoint orientation and scale, which keeps chance agreement at a few matches)."""
    min_floor_inliers: int = param(6, ge=3)
    """A floor pair needs at least this many inliers, counted once per keypoint spot (and no contradiction from its
    bearing-only estimate, checked as for a depth-backed pose; with fewer than floor_lone_inliers, another pair across
    its cut must agree). A chance fit between rooms that share no floor can reach this; the checks of its two rooms
    and its cut refuse it (docs/multi.md)."""
    floor_min_margin: float = param(2.0, ge=1)
    """A floor pose that the pair's images do not confirm (no bearing-only estimate of min_bearing_inliers) needs at
    least this many times the inliers of the best other translation at its yaw (FloorPose.second), where that one
    keeps min_floor_inliers or more: a repeated floor pattern seen from two rooms agrees nearly as well one pattern
    period along the baseline; fewer is the chance agreement any two floors leave somewhere."""
    floor_lone_inliers: int = param(11, ge=0)
    """A floor pose the images do not confirm with fewer inliers than this joins two sides of the registration only where
    the floor images of another pair across that cut also support it (register/cuts.py; a pair alone across its cut,
    as two panoramas alone, is refused too): between floors that share nothing a chance fit can reach
    min_floor_inliers, and no other pair agrees with it."""
    floor_beyond_rooms: int = param(9, ge=0)
    """A floor pose below floor_lone_inliers that no other pair across its cut supports is kept where at least this
    many of its inlier matches, and 90 % of them, lie beyond both rooms' walls: floor both panoramas see only through
    openings their depths close (a hallway between two rooms that no panorama stands in); a chance fit matches each
    room's own floor instead (chosen on synthetic layout tours, docs/multi.md). 0: never."""
    max_free_space_violation: float = param(0.05, ge=0, le=1)
    """A floor or layout pose is refused where both panoramas' depths hold their whole room (98 % of the pixels valid)
    and it puts more than this share of either view's surfaces inside the other's free space (0.15 m and 5 % nearer
    than that view's depth): two rooms that overlap (a right pose puts next to none there). The same test between any
    two registered panoramas removes the floor, layout or bearing-only edge the overlap rests on
    (solve.refuse_overlapping_rooms)."""
    manhattan: bool = True
    """Use each panorama's wall directions (panoworld/register/layout.py: manhattan_frame, from the depth's room
    outline; none where the outline is incomplete or not at right angles) where both panoramas of a pair have them:
    the pair's yaw is then one of 4 (the difference of the two modulo 90 degrees). A floor pair is fitted with its yaw
    fixed to those 4 (translation only), and a depth-backed, bearing-only or layout pose more than manhattan_tol_deg
    off them is refused."""
    manhattan_tol_deg: float = param(5.0, gt=0, le=45)
    """A pose's yaw must lie within this of one the wall directions allow."""
    layout: bool = False
    """Also try pairs that no depth, floor or bearing edge joins into one group with their layouts
    (panoworld/register/layout.py): a wall of one room against an opposed wall of the other, judged by where the
    images agree (the other room seen through a doorway). Off by default: rooms alike in shape and finish can be
    placed wrongly (docs/multi.md, Limits), and it costs 3-5 CPU s per pair tried."""
    layout_min_margin: float = param(1.5, gt=1)
    """A layout pair is trusted only when its best hypothesis' agreeing image area is at least this multiple of the
    best hypothesis distinct from it (farther than 0.3 m or 5 degrees)."""
    layout_min_score: float = param(250.0, ge=0)
    """... and at least this agreeing image area (pixels of the 96-row scoring grid, both directions, cos-latitude
    weighted)."""
