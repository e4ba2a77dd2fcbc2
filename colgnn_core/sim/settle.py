"""Does an object hold its shape under its own weight? The check ``colgnn scene new`` runs before writing a scene.

The ground truth settles every object under gravity on its support before frame 0 (:class:`.ipc.IPCSimulator`).
A soft material on a thin support (a cow's legs, glued at the hooves) can buckle there: the settled object then
lies far from the mesh that the scene's tool rest pose, workspace and trajectory family were derived from, and the
tool may never reach it. :func:`settle_report` measures the settling at the scene's resolution;
:func:`check_settle` refuses a scene that sags more than a fraction of its height, or is still moving when the
settle stops.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from colgnn_core.errors import InputError, SimulationError
from colgnn_core.sim.ipc import IPCSimulator

MAX_SAG_FRACTION = 0.15  # default refusal: a vertex settles farther than 15% of the object's height (the family's
                         # deepest press is 12% of the smallest side, so such a shape is not the one it was made for)


@dataclass(frozen=True)
class SettleReport:
    """How far an object moves while it settles under gravity (lengths in m)."""

    sag_m: float             # largest vertex displacement, settled against the mesh
    sag_fraction: float      # sag_m / the mesh's height (z extent)
    centroid_drop_m: float   # how far the vertex centroid moved down
    steps: int               # implicit settle steps taken
    converged: bool          # the last step moved less than the solver's tolerance
    wall_s: float

    def line(self) -> str:
        """One readable line, for a summary."""
        state = f"settled in {self.steps} steps" if self.converged else f"still moving after {self.steps} steps"
        return (f"under gravity the object sags {1e3 * self.sag_m:.1f} mm at most ({100 * self.sag_fraction:.1f}% of "
                f"its height; centroid down {1e3 * self.centroid_drop_m:.1f} mm), {state} ({self.wall_s:.0f} s)")


def settle_report(scene) -> SettleReport:
    """Settle ``scene``'s object under gravity with the ground-truth solver and measure the change."""
    t = time.perf_counter()
    sim = IPCSimulator(scene)  # reset() settles
    rest = np.asarray(scene.object.vertices, dtype=np.float64)
    x = sim.positions
    height = float(np.ptp(rest[:, 2]))
    sag = float(np.linalg.norm(x - rest, axis=1).max())
    return SettleReport(sag_m=sag, sag_fraction=sag / height if height > 0 else float("inf"),
                        centroid_drop_m=float(rest[:, 2].mean() - x[:, 2].mean()), steps=int(sim.settle_steps),
                        converged=bool(sim.settle_converged), wall_s=time.perf_counter() - t)


def check_settle(scene, max_sag_fraction: float = MAX_SAG_FRACTION) -> SettleReport:
    """:func:`settle_report`, raising :class:`InputError` (with what to change) when the object sags more than
    ``max_sag_fraction`` of its height, does not come to rest, or cannot be settled at all."""
    if not max_sag_fraction > 0:
        raise InputError(f"the largest allowed sag must be > 0, got {max_sag_fraction}")
    fixes = "use a stiffer material (e.g. --material 1e6,0.4,1000) or put it on the ground (--ground)"
    try:
        r = settle_report(scene)
    except SimulationError as exc:
        raise InputError(f"the object cannot be settled under its own weight ({exc}); {fixes}") from None
    if not r.converged:
        raise InputError(f"the object does not come to rest: {r.line()}; {fixes}")
    if r.sag_fraction > max_sag_fraction:
        accept = np.ceil(20 * r.sag_fraction) / 20
        raise InputError(f"the object does not hold its shape: {r.line()}, more than the allowed "
                         f"{100 * max_sag_fraction:.0f}%; {fixes}, or accept the sag with --max-sag {accept:.2f}")
    return r
