"""Scene registry: one TOML per scene in this folder; trajectory families in ``trajectories``."""

from __future__ import annotations

from functools import lru_cache

from colgnn_core.errors import InputError
from colgnn_core.scenes.scene import RESOLUTIONS, SCENE_DIR, Material, Scene, build_scene, read_config

SCENE_NAMES = ("cone_bunny", "knife_torus", "sphere_mat", "cylinder_banana")


def scene_names() -> list[str]:
    """Names of the scenes, in the paper's order."""
    return list(SCENE_NAMES)


def load_scene(name: str, resolution: str = "full") -> Scene:
    """The scene ``name`` at ``resolution`` ('full' | 'ci'). Cached: do not mutate the result.

    Raises InputError for an unknown name or resolution, listing the valid ones.
    """
    if name not in SCENE_NAMES:
        raise InputError(f"unknown scene {name!r}; valid scenes: {', '.join(SCENE_NAMES)}")
    if resolution not in RESOLUTIONS:
        raise InputError(f"unknown resolution {resolution!r}; valid: {', '.join(RESOLUTIONS)}")
    return _load(name, resolution)


@lru_cache(maxsize=None)
def _load(name: str, resolution: str) -> Scene:
    return build_scene(name, resolution, read_config(name))


from colgnn_core.scenes.trajectories import sample_poses, scripted_poses, split_seeds  # noqa: E402

__all__ = [
    "Material",
    "Scene",
    "RESOLUTIONS",
    "SCENE_DIR",
    "load_scene",
    "scene_names",
    "sample_poses",
    "scripted_poses",
    "split_seeds",
]
