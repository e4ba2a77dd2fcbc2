"""Renders: cross-sections are closed outlines; PNG and GIF files are written; bad output names are refused."""

import numpy as np
import pytest
import trimesh

from colgnn_core.errors import InputError
from colgnn_core.io import Sequence, save_sequence
from colgnn_core.evaluation.render import plane_section, render_file, tool_signed_distance


def _perimeter(segments: np.ndarray) -> float:
    return float(np.linalg.norm(segments[:, 1] - segments[:, 0], axis=1).sum())


def test_section_through_vertices_has_no_gaps():
    # An icosphere's equator is made of mesh vertices: the plane z = 0 runs exactly through them.
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    assert np.sum(np.abs(sphere.vertices[:, 2]) < 1e-12) > 10
    seg = plane_section(sphere.vertices, sphere.faces, np.zeros(3), np.array([0.0, 0.0, 1.0]))
    assert not np.isnan(seg).any()
    assert _perimeter(seg) == pytest.approx(2 * np.pi, rel=0.01)


def test_section_of_a_box_is_its_square_outline():
    box = trimesh.creation.box(extents=(2.0, 2.0, 2.0))
    seg = plane_section(box.vertices, box.faces, np.array([0.3, 0.0, 0.0]), np.array([1.0, 0.0, 0.0]))
    assert _perimeter(seg) == pytest.approx(8.0)
    np.testing.assert_allclose(seg[..., 0], 0.3)


def test_tool_signed_distance_is_negative_inside():
    box = trimesh.creation.box(extents=(2.0, 2.0, 2.0))
    d = tool_signed_distance(np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 3.0]]), box.vertices, box.faces)
    np.testing.assert_allclose(d, [-1.0, 2.0])


def _sequence(frames: int = 3) -> Sequence:
    obj = trimesh.creation.icosphere(subdivisions=1, radius=0.05)
    tool = trimesh.creation.box(extents=(0.02, 0.02, 0.02))
    lift = np.linspace(0.1, 0.04, frames)
    poses = np.array([[0.0, 0.0, z, 0.0, 0.0, 0.0, 1.0] for z in lift])
    return Sequence(np.repeat(obj.vertices[None], frames, 0), obj.faces,
                    np.stack([tool.vertices + [0, 0, z] for z in lift]), tool.faces, poses, 0.04)


@pytest.mark.parametrize("suffix", [".png", ".gif"])
def test_render_file_writes_pictures(tmp_path, suffix):
    save_sequence(tmp_path / "s.npz", _sequence())
    out = render_file(tmp_path / "s.npz", tmp_path / f"x{suffix}", count=2)
    head = out.read_bytes()[:4]
    assert head == (b"\x89PNG" if suffix == ".png" else b"GIF8")


def test_render_refuses_unknown_format(tmp_path):
    save_sequence(tmp_path / "s.npz", _sequence())
    with pytest.raises(InputError, match=".png or .gif"):
        render_file(tmp_path / "s.npz", tmp_path / "x.jpg")
