from setuptools import find_packages, setup

package_name = "uav_eval"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/uav_eval"]),
        ("share/uav_eval", ["package.xml"]),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="UAV collision avoidance maintainers",
    maintainer_email="maintainers@uav-collision-avoidance.dev",
    description="Measuring policies: crash tables, the validation choice, what decisions look at, figures and plots",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "evaluate = uav_eval.evaluate:main",
            "choose = uav_eval.selection:main",
            "grounding = uav_eval.grounding:main",
            "attention_figures = uav_eval.figures:main",
            "plot_curves = uav_eval.plots:main",
            "compare_models = uav_eval.compare_models:main",
            "world_maps = uav_eval.world_maps:main",
        ],
    },
)
