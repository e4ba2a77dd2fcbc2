"""Scene registry: one TOML per scene, the built-in ones in this folder and a user's on ``COLGNN_SCENE_PATH``;
trajectory families in ``trajectories``."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

from colgnn_core.errors import InputError
from colgnn_core.scenes.scene import (BUILTIN_SCENES, RESOLUTIONS, SCENE_DIR, SCENE_PATH_ENV, Material, Scene,
                                      build_scene, custom_scene_files, read_config_file, scene_dirs, scene_file)

SCENE_NAMES = BUILTIN_SCENES


def scene_names() -> list[str]:
    """Names of the scenes: the four built-in ones in the paper's order, then the user's (``COLGNN_SCENE_PATH``)."""
    return list(BUILTIN_SCENES) + sorted(custom_scene_files())


def is_custom(name: str) -> bool:
    """Is ``name`` a user's scene (a TOML on ``COLGNN_SCENE_PATH``)?"""
    return name not in BUILTIN_SCENES and scene_file(name) is not None


def load_scene(name: str, resolution: str = "full") -> Scene:
    """The scene ``name`` at ``resolution`` ('full' | 'ci'). Cached: do not mutate the result.

    Raises InputError for an unknown name or resolution, listing the valid ones.
    """
    path = scene_file(name)
    if path is None:
        hint = "" if scene_dirs() else f" (a scene made by `colgnn scene new` is found through {SCENE_PATH_ENV})"
        raise InputError(f"unknown scene {name!r}; valid scenes: {', '.join(scene_names())}{hint}")
    if resolution not in RESOLUTIONS:
        raise InputError(f"unknown resolution {resolution!r}; valid: {', '.join(RESOLUTIONS)}")
    return _load(name, resolution, str(path), path.stat().st_mtime_ns)


@lru_cache(maxsize=None)
def _load(name: str, resolution: str, path: str, _mtime_ns: int) -> Scene:
    """Cached by file and modification time: an edited TOML is read again."""
    folder = Path(path).parent
    return build_scene(name, resolution, read_config_file(Path(path)), base_dir=None if folder == SCENE_DIR else folder)


from colgnn_core.scenes.trajectories import sample_poses, scripted_poses, split_seeds  # noqa: E402

__all__ = [
    "Material",
    "Scene",
    "RESOLUTIONS",
    "SCENE_DIR",
    "SCENE_PATH_ENV",
    "is_custom",
    "load_scene",
    "scene_dirs",
    "scene_file",
    "scene_names",
    "sample_poses",
    "scripted_poses",
    "split_seeds",
]
