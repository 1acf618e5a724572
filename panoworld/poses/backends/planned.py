"""planned: the planned trajectory as it is (for generators that follow it exactly)."""

from __future__ import annotations

from panoworld.core.registry import register


def estimate(job):
    from panoworld.poses.estimate import planned_estimate

    return planned_estimate(job.planned)


register("poses", "planned", estimate, needs_plan=True, copies_plan=True, recovers=False)
