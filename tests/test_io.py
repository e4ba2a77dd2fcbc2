"""Contract formats: sequence .npz and poses CSV round trips and bad-input errors."""

import os

import numpy as np
import pytest

from colgnn_core.errors import InputError
from colgnn_core.geometry.transforms import (axis_angle_quat, interpolate_poses, inverse_transform_points,
                                             quat_to_matrix, transform_points, validate_pose)
from colgnn_core.io import Sequence, atomic_write, load_sequence, read_poses_csv, save_sequence, write_poses_csv


def _sequence(frames: int = 3) -> Sequence:
    rng = np.random.default_rng(0)
    poses = np.tile([0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0], (frames, 1))
    return Sequence(
        object_positions=rng.normal(size=(frames, 4, 3)),
        object_faces=np.array([[0, 1, 2], [0, 2, 3], [0, 3, 1], [1, 3, 2]]),
        tool_positions=rng.normal(size=(frames, 3, 3)),
        tool_faces=np.array([[0, 1, 2]]),
        tool_poses=poses,
        dt=0.04,
        extra={"step_ms": np.arange(frames, dtype=float)},
    )


def test_sequence_round_trip(tmp_path):
    seq = _sequence()
    save_sequence(tmp_path / "a.npz", seq)
    back = load_sequence(tmp_path / "a.npz")
    np.testing.assert_array_equal(back.object_positions, seq.object_positions)
    np.testing.assert_array_equal(back.tool_faces, seq.tool_faces)
    np.testing.assert_array_equal(back.extra["step_ms"], seq.extra["step_ms"])
    assert back.dt == 0.04 and back.frames == 3
    assert [p.name for p in tmp_path.iterdir()] == ["a.npz"], "no temporary file left behind"


def test_truncated_sequence_is_a_clear_error(tmp_path):
    save_sequence(tmp_path / "a.npz", _sequence())
    data = (tmp_path / "a.npz").read_bytes()
    (tmp_path / "b.npz").write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match="b.npz"):
        load_sequence(tmp_path / "b.npz")


def test_sequence_missing_key_and_nan(tmp_path):
    np.savez(tmp_path / "m.npz", object_positions=np.zeros((1, 3, 3)))
    with pytest.raises(InputError, match="missing keys"):
        load_sequence(tmp_path / "m.npz")
    seq = _sequence()
    seq.object_positions[1, 2, 0] = np.nan
    with pytest.raises(InputError, match="NaN"):
        save_sequence(tmp_path / "n.npz", seq)
    assert not (tmp_path / "n.npz").exists()


def test_sequence_bad_face_index(tmp_path):
    seq = _sequence()
    seq.object_faces[0, 0] = 99
    with pytest.raises(InputError, match="object_faces index out of range"):
        seq.validate()


def test_atomic_write_keeps_old_file_on_failure(tmp_path):
    target = tmp_path / "x.txt"
    target.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_write(target, "w") as fh:
            fh.write("new")
            raise RuntimeError("crash mid-write")
    assert target.read_text() == "old"
    assert os.listdir(tmp_path) == ["x.txt"]


def test_atomic_write_missing_folder(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        with atomic_write(tmp_path / "nope" / "x.txt", "w"):
            pass


def test_poses_csv_round_trip_and_normalisation(tmp_path):
    t = np.array([0.0, 0.04])
    q = axis_angle_quat([0, 1, 0], 0.3)
    poses = np.array([[0.1, 0.2, 0.3, *q], [0.1, 0.2, 0.25, *(q * (1 + 5e-4))]])
    write_poses_csv(tmp_path / "p.csv", t, poses)
    t2, p2 = read_poses_csv(tmp_path / "p.csv")
    np.testing.assert_allclose(t2, t)
    np.testing.assert_allclose(np.linalg.norm(p2[:, 3:], axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(p2[0], poses[0], atol=1e-15)


@pytest.mark.parametrize(
    "body, message",
    [
        ("t,px,py,pz,qx,qy,qz\n0,0,0,0,0,0,0\n", "missing column"),
        ("t,px,py,pz,qx,qy,qz,qw\n0,0,0,nan,0,0,0,1\n", "NaN"),
        ("t,px,py,pz,qx,qy,qz,qw\n0,0,0,0,0,0,0,2\n", "not unit length"),
        ("t,px,py,pz,qx,qy,qz,qw\n0,0,0,0,0,0,1\n", "expected 8 values"),
        ("t,px,py,pz,qx,qy,qz,qw\n0,0,0,zero,0,0,0,1\n", "not a number"),
        ("t,px,py,pz,qx,qy,qz,qw\n", "no pose rows"),
    ],
)
def test_malformed_poses_csv(tmp_path, body, message):
    (tmp_path / "p.csv").write_text(body)
    with pytest.raises(InputError, match=message):
        read_poses_csv(tmp_path / "p.csv")


def test_pose_validation_and_transforms():
    with pytest.raises(InputError, match="7 values"):
        validate_pose([0, 0, 0, 1])
    with pytest.raises(InputError, match="NaN or inf"):
        validate_pose([0, 0, np.inf, 0, 0, 0, 1])
    q = axis_angle_quat([0, 0, 1], np.pi / 2)
    r = quat_to_matrix(q)
    np.testing.assert_allclose(r @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    pose = np.array([1.0, 2.0, 3.0, *q])
    pts = np.array([[1.0, 0, 0], [0, 0, 1]])
    world = transform_points(pts, pose)
    np.testing.assert_allclose(world, [[1, 3, 3], [1, 2, 4]], atol=1e-12)
    np.testing.assert_allclose(inverse_transform_points(world, pose), pts, atol=1e-12)
    mid = interpolate_poses(np.array([0, 0, 0, 0, 0, 0, 1.0]), pose, [0.5])[0]
    np.testing.assert_allclose(mid[:3], [0.5, 1, 1.5])
    np.testing.assert_allclose(quat_to_matrix(mid[3:]) @ [1, 0, 0], [np.cos(np.pi / 4), np.sin(np.pi / 4), 0],
                               atol=1e-12)


def test_atomic_write_gives_usual_permissions(tmp_path):
    with atomic_write(tmp_path / "p.txt", "w") as fh:
        fh.write("x")
    umask = os.umask(0)
    os.umask(umask)
    assert (tmp_path / "p.txt").stat().st_mode & 0o777 == 0o666 & ~umask


def test_write_generated_section_replaces_only_its_block(tmp_path):
    """The block between the markers is replaced; text around it is kept; a missing file or block is created;
    broken markers are refused and leave the file as it was."""
    from colgnn_core.io import write_generated_section

    page = tmp_path / "p.md"
    write_generated_section(page, "t", "| a |\n")
    assert page.read_text() == "<!-- begin t -->\n| a |\n<!-- end t -->\n"
    page.write_text("head\n<!-- begin t -->\nold\n<!-- end t -->\ntail\n")
    write_generated_section(page, "t", "new")
    assert page.read_text() == "head\n<!-- begin t -->\nnew\n<!-- end t -->\ntail\n"
    write_generated_section(page, "u", "other")  # another block is appended, the first stays
    assert page.read_text().endswith("tail\n\n<!-- begin u -->\nother\n<!-- end u -->\n") and "new" in page.read_text()
    broken = "x\n<!-- end t -->\n<!-- begin t -->\n"
    page.write_text(broken)
    with pytest.raises(InputError, match="must each appear once"):
        write_generated_section(page, "t", "new")
    assert page.read_text() == broken
