from glob import glob

from setuptools import find_packages, setup

package_name = "uav_sim"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/uav_sim"]),
        ("share/uav_sim", ["package.xml"]),
        ("share/uav_sim/worlds", glob("worlds/*.yaml")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="UAV collision avoidance maintainers",
    maintainer_email="maintainers@uav-collision-avoidance.dev",
    description="pybullet quadrotor simulator with a depth camera, the paper's reward and worlds",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "sim_node = uav_sim.sim_node:main",
        ],
    },
)
