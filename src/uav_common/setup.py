from setuptools import find_packages, setup

package_name = "uav_common"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    package_data={"uav_common": ["fastdds_large_frames.xml"]},
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/uav_common"]),
        ("share/uav_common", ["package.xml"]),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="UAV collision avoidance maintainers",
    maintainer_email="maintainers@uav-collision-avoidance.dev",
    description="The ROS contract, parameter declaration and node runner shared by the uav_* nodes",
    license="Apache-2.0",
)
