"""policy_node's parameters, declared once (uav_common.settings): the ROS declarations, params/policy.yaml
and docs/PARAMETERS.md come from here."""

from __future__ import annotations

import dataclasses

from uav_common.actions import ActionSettings
from uav_common.ros_params import ParameterError
from uav_common.settings import setting

from .networks import MAX_FRAMES, NetConfig
from .safety import SafetySettings
from .shield import ShieldSettings

# Parameters retired, and why: a node given one stops at start-up and says so.
RETIRED = {
    "ensemble_rule": "several weights files always act on their mean Q-values (the min rule did not help)",
    "sam_readout": "SAM's readout comes from the weights files (and pushes), like their layer sizes",
}


@dataclasses.dataclass(frozen=True)
class PolicySettings:
    """policy_node's parameters."""

    model: str = setting("sam", "Q-network: sam (D3QN-SAM, attention) or cnn (D3QN-CNN)", choices=("sam", "cnn"))
    weights: str = setting(
        "",
        "safetensors weights file, or several separated by commas, flown as one policy on the mean of their Q-values "
        "(e.g. a run's snapshots and final weights); a folder: its .safetensors files; empty: "
        "the packaged weights",
    )
    epsilon: float = setting(
        0.0,
        "Probability of a random action (exploration); while training, the trainer's pushes change it and the parameter "
        "shows the value in use (a user's set is refused)",
        0.0,
        1.0,
        read_only=False,
    )
    seed: int = setting(0, "Seed for the random initialisation and for exploration", 0, 2**31 - 1)
    device: str = setting(
        "auto", "Torch device: auto (cuda when present, else cpu), cpu or cuda", choices=("auto", "cpu", "cuda")
    )
    step_duration_s: float = setting(
        0.5,
        "Duration of one step the weights were trained with (s; sim_node's step_duration_s): the frame stack holds frames "
        "this far apart, whatever the camera's rate",
        0.01,
        5.0,
    )
    control_rate_hz: float = setting(
        15.0,
        "With a camera (no simulator): commands at most this often, each on the newest frame (a frame is answered as it "
        "arrives, or at the next control tick); a simulator's frames are each answered",
        0.5,
        200.0,
    )
    publish_stamped: bool = setting(
        False, "Also publish cmd_vel_stamped (TwistStamped: the frame's stamp, the vehicle's base_link), for flight stacks"
    )
    safety: SafetySettings = SafetySettings()
    shield: ShieldSettings = ShieldSettings()
    actions: ActionSettings = ActionSettings()
    frame_stack: int = setting(NetConfig.frames, "Depth frames in the state", 1, MAX_FRAMES)
    local_map: bool = setting(
        False,
        "The network takes the local map of the frames and odom (NetConfig.local_map) when no weights file is given "
        "(train sets it); a weights file's header says so itself",
    )
    input_height: int = setting(
        64, "Network input height (px); frames of another size keep the nearest depth of each cell", 8, 512
    )
    input_width: int = setting(64, "Network input width (px)", 8, 512)
    max_range_m: float = setting(10.0, "Depth normalisation range (m); match sim_node's max_range_m", 0.5, 100.0)
    publish_overlay: bool = setting(
        True, "Publish attention/overlay (SAM) or saliency/overlay (CNN), rgb8, when someone subscribes"
    )
    insight_every: int = setting(
        5,
        "Measure what the decision looks at (uav_policy.insight: sharpness, variation, deletion test, grounding) on every "
        "Nth answered frame, reported on /diagnostics; 0: never",
        0,
        10000,
    )
    insight_window: int = setting(200, "The measured frames /diagnostics summarises (the newest)", 1, 1000000)
    accept_pushes: bool = setting(
        False,
        "Serve ~/push_weights, which swaps in weights and epsilon (train sets true); false: a flying policy takes "
        "nothing from the network",
    )
    push_key_file: str = setting(
        "",
        "accept_pushes: the run's key (hex, mode 0600; train writes it, trainer_node creates it when missing); only "
        "pushes signed with it are taken. Read at the first push",
    )
    source: str = setting(
        "auto",
        "Where frames come from: auto (a camera until a simulator's step_outcome publisher is discovered: a frame "
        "that comes first is answered as a camera's); simulator (every frame waits for its step outcome: fly and evaluate "
        "set it, train's wait_for_trainer implies it; the first frames of a lockstep flight are answered as in process)",
        choices=("auto", "simulator"),
    )
    wait_for_trainer: bool = setting(
        False,
        "Lockstep learning (train sets true): answer a frame only once trainer_node releases it over ~/push_weights "
        "(with the weights of its updates so far and the epsilon; the trainer learns while the policy acts)",
    )
    wait_for_trainer_timeout_s: float = setting(
        10.0,
        "wait_for_trainer: a frame held this long is answered anyway, with a warning (the run is then no longer in lockstep)",
        0.1,
        3600.0,
    )
    torch_threads: int = setting(1, "Torch intra-op threads (batch-1 inference gains nothing from more)", 1, 256)
    camera_switch_s: float = setting(
        2.0,
        "Frames of another frame_id than the stacked camera's are dropped (ERROR on /diagnostics); that camera is taken, "
        "with a new stack, once the stacked one has sent nothing for this long (s)",
        0.1,
        3600.0,
    )

    def check(self) -> None:
        """ParameterError, naming the parameter, for settings that do not go together."""
        if self.wait_for_trainer and not self.accept_pushes:
            raise ParameterError("parameter 'wait_for_trainer': frames are released by pushes, so it needs accept_pushes:=true")
        if self.accept_pushes and not self.push_key_file:
            raise ParameterError("parameter 'accept_pushes': needs 'push_key_file', the key pushes are signed with")
        if self.accept_pushes and self.shield.shield == "always":
            raise ParameterError(
                "parameter 'shield': a policy that takes pushes (training) flies the network's own actions; "
                "set shield:=never (train does)"
            )
        if self.accept_pushes and self.safety.safety:
            # The trainer learns from `action`, the network's choice: the vehicle must fly exactly that.
            raise ParameterError(
                "parameter 'safety': a policy that takes pushes (training) flies the network's own actions; "
                "set safety:=false (train does)"
            )

    def describe(self, parameters: int, source: str, device, hfov_deg: float | None) -> str:
        """policy_node's start-up line: what flies, how, and what explains it."""
        camera = f", trained with a {hfov_deg:g} deg camera" if hfov_deg is not None else ""
        sf = self.safety
        safety = (
            f"safety layer on (stop after {sf.frame_timeout_s:g} s without camera frames, "
            f"stop distance {sf.stop_distance_m:g} m); "
            if sf.safety
            else "safety layer off; "
        )
        lockstep = "answering each frame once trainer_node releases it (lockstep learning); " if self.wait_for_trainer else ""
        att = "attention on attention, attention/overlay, attention/weights"
        att = att if self.model == "sam" else "cnn has no attention module: its Grad-CAM saliency on saliency, saliency/overlay"
        if self.insight_every:
            att += f"; what it looks at measured every {self.insight_every} frame(s) on /diagnostics"
        return (
            f"model {self.model} ({parameters} parameters, {source}{camera}) on {device}; epsilon {self.epsilon}; "
            f"{safety}{lockstep}{att}"
        )
