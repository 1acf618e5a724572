"""Notes under the run table that read several stages' artifacts: a home whose floor is NavMesh pieces that do not connect."""

from __future__ import annotations

from pathlib import Path

from panoworld.io.jsonio import read_json
from panoworld.register.artifact import read_registration
from panoworld.register.inputs import REGISTRATION_JSON
from panoworld.register.options import BEYOND_SHARE


def floor_pieces_note(navmesh_artifact: Path, register_artifact: Path | None = None) -> str | None:
    """"home: the floor is 2 NavMesh pieces that do not connect (a, b | c), so the trajectory cuts between them: ..."
    when a home's NavMesh holds its capture points on more than one piece (the navmesh manifest's info.components),
    with floor_joins and what joins the pieces; None otherwise."""
    comps = read_json(Path(navmesh_artifact) / "manifest.json", default={}).get("info", {}).get("components") or []
    if len(comps) < 2:
        return None
    registration = None
    if register_artifact is not None and (Path(register_artifact) / REGISTRATION_JSON).is_file():
        registration = read_registration(register_artifact)[1]
    why = floor_joins(comps, registration)
    groups = " | ".join(", ".join(c.get("capture_points", [])) for c in comps)
    return (f"home: the floor is {len(comps)} NavMesh pieces that do not connect ({groups}), so the trajectory cuts "
            f"between them{': ' + '; '.join(why) if why else ''}; a panorama taken where their floors meet joins them "
            "(docs/multi.md)")


def floor_joins(components: list[dict], registration: dict | None) -> list[str]:
    """For each registration edge (registration.json's parent and edge of a panorama) between capture points on two
    of a home's NavMesh pieces (the navmesh info's components): what joined the two panoramas without joining their
    floors, floor both see beyond their own rooms' walls (a hallway no depth holds) or a pose through no open
    doorway."""
    piece = {n: k for k, c in enumerate(components) for n in c.get("capture_points", [])}
    rows = (registration or {}).get("panoramas", {})
    why = []
    for n, row in rows.items():
        parent = row.get("parent") if isinstance(row, dict) else None
        if parent is None or n not in piece or parent not in piece or piece[n] == piece[parent]:
            continue
        beyond, matched = int(row.get("beyond_rooms", 0)), int(row.get("inlier_matches", 0))
        if row.get("edge") == "floor" and matched and beyond >= BEYOND_SHARE * matched:
            why.append(f"{parent} and {n} see one floor beyond both rooms' walls ({beyond} of {matched} floor matches), "
                       "which no panorama's depth holds (a hallway)")
        else:
            why.append(f"{parent} and {n} are joined by a {row.get('edge', 'given')} pose, but no doorway between their "
                       "floors was seen open")
    return why
