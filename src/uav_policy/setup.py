from glob import glob

from setuptools import find_packages, setup

package_name = "uav_policy"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/uav_policy"]),
        ("share/uav_policy", ["package.xml"]),
        ("share/uav_policy/weights", glob("weights/*.md")),
        ("share/uav_policy/weights/sam", glob("weights/sam/*.safetensors")),
        ("share/uav_policy/weights/cnn", glob("weights/cnn/*.safetensors")),
        ("share/uav_policy/weights/distilled/sam", glob("weights/distilled/sam/*.safetensors")),
        ("share/uav_policy/weights/wide150/sam", glob("weights/wide150/sam/*.safetensors")),
        ("share/uav_policy/weights/wide150/cnn", glob("weights/wide150/cnn/*.safetensors")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="UAV collision avoidance maintainers",
    maintainer_email="maintainers@uav-collision-avoidance.dev",
    description="D3QN-SAM and D3QN-CNN policies and the policy node that publishes attention maps",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "policy_node = uav_policy.policy_node:main",
        ],
    },
)
