from glob import glob

from setuptools import find_packages, setup

package_name = "uav_trainer"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/uav_trainer"]),
        ("share/uav_trainer", ["package.xml"]),
        ("share/uav_trainer/launch", glob("launch/*.launch.py")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="UAV collision avoidance maintainers",
    maintainer_email="maintainers@uav-collision-avoidance.dev",
    description="Replay memory, the Double-Dueling DQN learner, weight pushes and checkpoints",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "trainer_node = uav_trainer.trainer_node:main",
            "train = uav_trainer.train:main",
            "distill = uav_trainer.distill:main",
            # moved to uav_eval: each says so and stops (kept one release)
            *(
                f"{exe} = uav_trainer.moved:{exe}"
                for exe in ("evaluate", "choose", "grounding", "attention_figures", "plot_curves")
            ),
        ],
    },
)
