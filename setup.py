"""colgnn: an ament_python package (colcon/ros2 run) that also installs with plain pip."""

from setuptools import find_packages, setup

PACKAGE = "colgnn_ros"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(include=["colgnn_core", "colgnn_core.*", "colgnn_ros", "colgnn_ros.*", "msg_tools",
                                    "msg_tools.*"]),
    package_data={"colgnn_core": ["scenes/*.toml", "assets/meshes/*", "assets/models/*", "assets/ccd/**/*"],
                  "colgnn_ros": ["*.xml"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
    ],
    python_requires=">=3.10",
    install_requires=["numpy", "scipy", "threadpoolctl", "trimesh", "ipctk", "numba", "tqdm", "matplotlib", "meshio"],
    zip_safe=False,
    maintainer="colgnn developers",
    maintainer_email="dev@colgnn.invalid",
    description="Collision-aware GNN simulation of tool-object contact, real time on a CPU, with ROS 2 nodes.",
    license="MIT",
    entry_points={
        "console_scripts": [
            "colgnn = colgnn_core.cli:main",
            "pose_publisher = colgnn_ros.pose_publisher_node:main",
            "predictor = colgnn_ros.predictor_node:main",
            "colgnn_demo = colgnn_ros.demo:main",
            "colgnn_bench_latency = colgnn_ros.bench_latency:main",
        ],
    },
)
