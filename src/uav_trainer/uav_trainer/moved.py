"""Commands that moved to uav_eval, the measuring package (kept one release): each says where it went and stops,
so that no script keeps running the old name silently."""

from __future__ import annotations

import sys

MOVED = ("evaluate", "choose", "grounding", "attention_figures", "plot_curves")


def _moved(exe: str):
    def main(argv=None) -> int:
        print(
            f"`ros2 run uav_trainer {exe}` has moved: run `ros2 run uav_eval {exe}` with the same arguments "
            "(measuring is its own package now)",
            file=sys.stderr,
        )
        return 2

    return main


evaluate, choose, grounding, attention_figures, plot_curves = (_moved(exe) for exe in MOVED)
