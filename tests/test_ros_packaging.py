"""`colcon build` installs the ament_python package, and the installed `pose_publisher` and `predictor` run.

colcon (colcon-common-extensions, from PyPI) runs with this interpreter on a copy of the package
sources in a tmp folder, so no build/ install/ log/ folders appear in the repository:

    python -m colcon --log-base LOG build --base-paths SRC \
        --build-base BUILD --install-base INSTALL --merge-install

colcon calls ``setup.py`` with ``sys.executable``, so console scripts get this interpreter in their
shebang (the venv's python, which re-executes itself with the ROS wheels' library path); nothing
needs to be on PATH. ``--merge-install`` only gives the flat ``INSTALL/lib/colgnn_ros/...`` layout
of a ROS workspace. The installed tree is then used the ROS way (``source INSTALL/setup.bash``),
from a folder outside the sources, with PYTHONPATH cleared first.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import uuid
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rclpy")

pytest.importorskip("colcon_core")
if shutil.which("bash") is None:
    pytest.skip("needs bash to source the colcon setup script", allow_module_level=True)

from geometry_msgs.msg import PoseStamped  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402
from visualization_msgs.msg import Marker  # noqa: E402

from colgnn_ros.common import OUTPUT_QOS, POSE_QOS  # noqa: E402
from msg_tools import array_to_pose_stamped, parse_marker_cdr  # noqa: E402
from tests.helpers import train_data as fx  # noqa: E402
from tests.helpers.ros import ros_env, spin_until  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
PY = sys.executable
PKG = "colgnn_ros"
# What setup.py / package.xml need; the Python packages are copied whole (minus caches).
SOURCES = ("setup.py", "setup.cfg", "package.xml", "resource", "colgnn_core", "colgnn_ros", "msg_tools")
EXECUTABLES = ("colgnn", "pose_publisher", "predictor")
PY_DIR = f"lib/python{sys.version_info.major}.{sys.version_info.minor}/site-packages"

INSPECT = r"""
import json, os
from ament_index_python.packages import get_package_prefix, get_package_share_directory
import colgnn_core, colgnn_ros, msg_tools
from colgnn_core.scenes import load_scene, scene_names
prefix = get_package_prefix("colgnn_ros")
lib = os.path.join(prefix, "lib", "colgnn_ros")  # where `ros2 run colgnn_ros X` looks
print(json.dumps({
    "prefix": prefix,
    "share": get_package_share_directory("colgnn_ros"),
    "executables": sorted(f for f in os.listdir(lib) if os.access(os.path.join(lib, f), os.X_OK)),
    "modules": [m.__file__ for m in (colgnn_core, colgnn_ros, msg_tools)],
    # every scene TOML at "ci"; cone_bunny at "full" reads the other bunny asset (bunny.msh)
    "scenes": {f"{n}/{r}": load_scene(n, r).object.num_vertices
               for n, r in [(n, "ci") for n in scene_names()] + [("cone_bunny", "full")]},
}))
"""


def _copy_sources(dst: Path) -> None:
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "*.egg-info")
    dst.mkdir(parents=True)
    for name in SOURCES:
        src = REPO / name
        if src.is_dir():
            shutil.copytree(src, dst / name, ignore=ignore)
        else:
            shutil.copy2(src, dst / name)


@pytest.fixture(scope="module")
def colcon_install(tmp_path_factory) -> Path:
    """Build the package with colcon into a tmp workspace; returns the install base."""
    ws = tmp_path_factory.mktemp("colcon_ws")
    _copy_sources(ws / "src" / PKG)
    env = {k: v for k, v in os.environ.items()
           if k not in ("PYTHONPATH", "AMENT_PREFIX_PATH", "COLCON_PREFIX_PATH", "COLCON_DEFAULTS_FILE")}
    env["COLCON_HOME"] = str(ws / "colcon_home")  # no user defaults (e.g. --symlink-install) or mixins
    cmd = [PY, "-m", "colcon", "--log-base", str(ws / "log"), "build", "--base-paths", str(ws / "src"),
           "--build-base", str(ws / "build"), "--install-base", str(ws / "install"), "--merge-install",
           "--event-handlers", "console_direct-"]
    res = subprocess.run(cmd, cwd=ws, env=env, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stdout + res.stderr
    return ws / "install"


def sourced(install: Path, command: str) -> list[str]:
    """bash command line that sources the workspace (as a user would) and then runs ``command``."""
    return ["bash", "-c", f'unset PYTHONPATH AMENT_PREFIX_PATH; source "{install}/setup.bash" && {command}']


def test_colcon_installs_executables_index_and_package_data(colcon_install):
    inst = colcon_install
    for exe in EXECUTABLES:
        path = inst / "lib" / PKG / exe
        assert path.is_file() and os.access(path, os.X_OK), path
        assert path.read_text().splitlines()[0] == f"#!{PY}"  # the interpreter that ran colcon
    assert (inst / "share/ament_index/resource_index/packages" / PKG).is_file()
    assert (inst / "share" / PKG / "package.xml").read_bytes() == (REPO / "package.xml").read_bytes()
    site = inst / PY_DIR
    for pattern in ("colgnn_core/scenes/*.toml", "colgnn_core/assets/meshes/*", "colgnn_ros/*.xml"):
        installed = {p.relative_to(site) for p in site.glob(pattern)}
        source = {p.relative_to(REPO) for p in REPO.glob(pattern) if p.is_file()}
        assert source and installed == source, pattern


def test_installed_package_works_outside_the_source_tree(colcon_install, tmp_path):
    inst = colcon_install.resolve()
    res = subprocess.run(sourced(inst, f'exec "{PY}" -c \'{INSPECT}\''), cwd=tmp_path,
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stdout + res.stderr
    info = json.loads(res.stdout.strip().splitlines()[-1])
    assert Path(info["prefix"]) == inst and Path(info["share"]) == inst / "share" / PKG
    assert set(EXECUTABLES) <= set(info["executables"])
    for module in info["modules"]:  # the installed copy, not the repository (nor the venv's editable install)
        assert Path(module).is_relative_to(inst / PY_DIR), module
    assert all(n > 0 for n in info["scenes"].values()) and len(info["scenes"]) == 5


def test_installed_pose_publisher_publishes_and_stops_on_sigterm(colcon_install, node, ros, tmp_path):
    _, executor, domain = ros
    topic = f"/test_{uuid.uuid4().hex[:12]}/tool_pose"  # this test's alone, whatever else runs on the domain
    got: list[PoseStamped] = []
    node.create_subscription(PoseStamped, topic, got.append,
                             QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT))
    inst = colcon_install.resolve()
    command = (f'exec "{inst}/lib/{PKG}/pose_publisher" --ros-args -r tool_pose:={topic} '
               "-p trajectory:=stab -p rate:=50.0 -p frames:=500")
    proc = subprocess.Popen(sourced(inst, command), cwd=tmp_path, env=ros_env(domain),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        assert spin_until(executor, lambda: len(got) >= 5, timeout=30.0), "no poses from the installed executable"
        proc.send_signal(signal.SIGTERM)  # `exec`: the bash pid is the node's
        out, _ = proc.communicate(timeout=15)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, out
    assert "publishing 500 poses ('stab' of sphere_mat)" in out and "Traceback" not in out, out


def test_installed_predictor_publishes_meshes_and_stops_on_sigint(colcon_install, node, ros, tmp_path):
    """`lib/colgnn_ros/predictor` (what `ros2 run colgnn_ros predictor` starts) steps poses into meshes."""
    _, executor, domain = ros
    ns = f"/test_{uuid.uuid4().hex[:12]}"
    checkpoint = fx.trained_checkpoint("full")
    poses = fx.scene().check_poses(fx.scene().tool_rest_pose[None])
    meshes: list[bytes] = []
    node.create_subscription(Marker, f"{ns}/deformed_mesh", meshes.append, OUTPUT_QOS, raw=True)
    pub = node.create_publisher(PoseStamped, f"{ns}/tool_pose", POSE_QOS)
    inst = colcon_install.resolve()
    command = (f'exec "{inst}/lib/{PKG}/predictor" --ros-args -r __ns:={ns} -r /diagnostics:={ns}/diagnostics '
               f"-p scene:={fx.SCENE} -p checkpoint:={checkpoint} -p threads:=1 -p compile:=false")
    proc = subprocess.Popen(sourced(inst, command), cwd=tmp_path, env=ros_env(domain),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        # The installed copy's sources are new files, so numba compiles every kernel afresh (jit_cache.py): 149 s
        # beside a 1-core solver run on the 2-core test machine (15 s warm).
        assert spin_until(executor, lambda: pub.get_subscription_count() == 1 or proc.poll() is not None,
                          timeout=300.0), "the installed predictor did not subscribe"
        for _ in range(30):  # best-effort: repeat the (rest) pose until the node's reader has matched ours
            pub.publish(array_to_pose_stamped(poses[0], "world", node.get_clock().now().nanoseconds))
            if spin_until(executor, lambda: len(meshes) >= 2, timeout=1.0):
                break
        assert len(meshes) >= 2, "no mesh from the installed node"
        proc.send_signal(signal.SIGINT)  # `exec`: the bash pid is the node's
        out, _ = proc.communicate(timeout=15)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, out
    assert f"scene {fx.SCENE} (ci)" in out and "Traceback" not in out, out
    m = parse_marker_cdr(meshes[-1])
    assert m.corners.shape == (len(fx.scene().object.faces), 3, 3) and np.isfinite(m.corners).all()
