"""GPS that disagrees with the photos' reconstruction, judged on a finished model (`gps_disagrees`)
and while the mapping with the GPS as pose priors is still growing (`MappingWatch`).

A camera's own receiver can drift by tens of metres in height over a flight (docs/POSES.md, "GPS
that disagrees"). COLMAP's bundle adjustment with such priors fights the photos: on a 57-photo
flight it placed 20 photos in the time the mapping without them placed all 57, and its model
then disagreed with the GPS anyway. The watch looks at the model as it grows: after
each photo placed, from `CHECK_MIN` photos on, the placed cameras turned z-up
(`normalize.z_up_turn`) and fitted to their fixes (`georef.ransac_similarity` about z, as
`georef.align_model` fits the finished model); when half of them or more lie over
`georef.INLIER_METRES` from their fixes, the mapping stops there (`GpsStopped`) and `poses` maps
without the priors at once, instead of after a whole mapping with them (on that flight, when
20 photos were placed: the prior pulls the early cameras onto their fixes).
"""

from __future__ import annotations

import numpy as np

from jaxnerf_grid.capture import georef
from jaxnerf_grid.data.normalize import z_up_turn

CHECK_MIN = 10   # placed photos before the growing model is judged: a fit to a few cameras is noise


def gps_disagrees(far: int, registered: int) -> str | None:
    """Why the GPS is not to be trusted when the GPS residuals' outliers (far of the registered
    photos) are half of them or more: then the receiver (a camera's own GPS that lags the
    shutter or drifts in height) or the model as a whole (a part of it registered turned) is
    wrong, not a few photos, and leaving those photos out is no cure: `poses` maps again without
    the GPS priors, and georeferences without the GPS when it still disagrees. None under half."""
    if registered <= 0 or far < 0.5 * registered:
        return None
    return (f"the GPS disagrees with the photos' reconstruction ({far} of {registered} registered photos more than "
            f"{georef.INLIER_METRES:.0f} m from their fixes): a receiver that lags or drifts, or photos registered "
            "in the wrong place")


def far_from_fixes(c2w: dict, fixes: dict) -> tuple[int, int]:
    """How many placed cameras lie over `georef.INLIER_METRES` from their GPS fixes.

    c2w: {photo name: camera-to-world [4, 4], OpenGL axes} in the model's frame (any scale,
    any turn); fixes: {photo name: [3] local metres, z up}. The cameras with a fix are turned so
    their up axis is +z and fitted to the fixes by a robust similarity about z. Returns (far,
    placed): placed, the cameras with a fix; (0, placed) under 3 of them (no fit)."""
    names = [name for name in c2w if name in fixes]
    if len(names) < 3:
        return 0, len(names)
    poses = np.stack([np.asarray(c2w[name], np.float64) for name in names])
    turn = z_up_turn(poses)
    src = poses[:, :3, 3] @ turn.T
    dst = np.stack([np.asarray(fixes[name], np.float64) for name in names])
    sim, _ = georef.ransac_similarity(src, dst, georef.INLIER_METRES, yaw_only=True)
    error = np.linalg.norm(georef.apply_similarity(sim, src) - dst, axis=1)
    return int(np.sum(error > georef.INLIER_METRES)), len(names)


class GpsStopped(Exception):
    """The mapping with GPS priors was stopped: the model so far disagrees with the GPS."""

    def __init__(self, far: int, placed: int):
        super().__init__(f"the GPS disagrees with the first {placed} photos' reconstruction ({far} of them more than "
                         f"{georef.INLIER_METRES:.0f} m from their fixes)")
        self.far, self.placed = far, placed


class MappingWatch:
    """Judges a growing model after each photo placed, from `CHECK_MIN` photos on: `check(c2w)`
    with the placed cameras ({name: [4, 4]}, `far_from_fixes`) raises GpsStopped when
    `gps_disagrees`. `stopped`: {"far", "placed"} once it has, else None; `checks`: how many
    times it judged."""

    def __init__(self, fixes: dict):
        self.fixes, self.checks = fixes, 0
        self.stopped: dict[str, int] | None = None

    @staticmethod
    def due(placed: int) -> bool:
        """Whether a model of `placed` photos is judged."""
        return placed >= CHECK_MIN

    def check(self, c2w: dict) -> None:
        self.checks += 1
        far, placed = far_from_fixes(c2w, self.fixes)
        if gps_disagrees(far, placed) is not None:
            self.stopped = {"far": far, "placed": placed}
            raise GpsStopped(far, placed)
