from glob import glob

from setuptools import find_packages, setup

package_name = "uav_bringup"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/uav_bringup"]),
        ("share/uav_bringup", ["package.xml"]),
        ("share/uav_bringup/launch", glob("launch/*.launch.py")),
        ("share/uav_bringup/foxglove", glob("foxglove/*.json")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="UAV collision avoidance maintainers",
    maintainer_email="maintainers@uav-collision-avoidance.dev",
    description="Flying and watching the stack: fly, record (MCAP bags) and live_view (Foxglove)",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "fly = uav_bringup.fly:main",
            "record = uav_bringup.record:main",
            "live_view = uav_bringup.live_view:main",
            "mavlink_bridge = uav_bringup.mavlink_bridge:main",
        ],
    },
)
