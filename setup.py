"""ament_python / pip installation of cegc_ros.

Installs the Python packages ``cegc_ros`` and ``msg_adapters``, the ament index marker,
``package.xml``, the parameter files and the shipped weights under ``share/cegc_ros`` (the only
copy of the weights: ``cegc_ros.paths.shipped_weights`` finds them there through the ament
index) and the console scripts (into ``lib/cegc_ros`` via setup.cfg, which is where ``ros2 run``
looks). Every console script goes through ``cegc_ros.entry_points``, which preloads jemalloc.
"""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "cegc_ros"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(include=["cegc_ros", "cegc_ros.*", "msg_adapters", "msg_adapters.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/params", glob("params/*.yaml") + glob("params/*.xml")),
        (f"share/{PACKAGE}/weights", glob(f"{PACKAGE}/weights/*.pt") + glob(f"{PACKAGE}/weights/*.onnx")
         + glob(f"{PACKAGE}/weights/*.json")),
    ],
    install_requires=["setuptools"],
    zip_safe=False,
    maintainer="cegc_ros maintainers",
    maintainer_email="cegc-ros@example.org",
    description="CEGC partial point-cloud registration for ROS 2",
    license="Apache-2.0",
    python_requires=">=3.10",
    entry_points={
        "console_scripts": [
            "register_node = cegc_ros.entry_points:register_node",
            "register_lifecycle_node = cegc_ros.entry_points:register_lifecycle_node",
            "cegc-register = cegc_ros.entry_points:cegc_register",
            "cegc-demo = cegc_ros.entry_points:cegc_demo",
            "cegc-eval = cegc_ros.entry_points:cegc_eval",
            "cegc-eval-seq = cegc_ros.entry_points:cegc_eval_seq",
            "cegc-make-bag = cegc_ros.entry_points:cegc_make_bag",
            "cegc-make-pairs = cegc_ros.entry_points:cegc_make_pairs",
            "cegc-replay = cegc_ros.entry_points:cegc_replay",
            "cegc-train = cegc_ros.entry_points:cegc_train",
        ],
    },
)
