"""The packaged policies fly exactly as they did: a short in-process flight of each packaged set, with its crashes,
reward and turning pinned. A change to how a frame becomes a command (or to the files) shows here first; update the
numbers in the commit that explains the change."""

from pathlib import Path

import pytest

from uav_eval.flights import ENSEMBLE_SEP, FlightSpec, evaluate_inprocess

WEIGHTS = Path(__file__).resolve().parents[2] / "src" / "uav_policy" / "weights"
# folder: (model, crashes, mean reward per step, turning steps) over 150 steps of Complex, random start headings,
# simulator seed 3, each set behind the camera it was trained behind (sam/, cnn/: the realsense_d435 sensor).
PINNED = {
    "sam": ("sam", 0, 1.5552721636507951, 58),
    "cnn": ("cnn", 0, 1.7648285925957639, 56),
    "wide150/sam": ("sam", 2, 2.3991461638615923, 64),
    "wide150/cnn": ("cnn", 0, 3.089693096952854, 53),
}


@pytest.mark.parametrize("folder", sorted(PINNED))
def test_each_packaged_set_flies_as_pinned(folder):
    model, crashes, reward, turns = PINNED[folder]
    files = sorted((WEIGHTS / folder).glob("*.safetensors"))
    assert len(files) >= 1, folder
    r = evaluate_inprocess(FlightSpec(model, ENSEMBLE_SEP.join(map(str, files)), "complex", 150, 3, 180.0, insight_every=0))
    assert (r.crashes, r.turn_steps) == (crashes, turns) and r.mean_reward == pytest.approx(reward, abs=1e-6), (
        f"{folder} flies differently: {r.crashes} crashes, reward {r.mean_reward!r}, {r.turn_steps} turning steps"
    )
